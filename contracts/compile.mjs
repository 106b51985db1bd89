// Compiles every contracts/*.sol with the pinned solc-js and writes one artifact per deployable
// contract: contracts/build/<Name>.json (ABI, bytecode, compiler version and settings, source
// digest) for the services, and clients/robocloud/abi/<Name>.json (ABI only) shipped inside the
// SDK package, which must not read repository paths.
//
// Usage: node contracts/compile.mjs [--build-dir DIR] [--abi-dir DIR]
// The output is deterministic, so a test recompiles into a temporary directory and compares.
import { createHash } from "node:crypto";
import { mkdirSync, readdirSync, readFileSync, writeFileSync } from "node:fs";
import { createRequire } from "node:module";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath } from "node:url";

const require = createRequire(import.meta.url);
const solc = require("solc");

const CONTRACTS_DIR = dirname(fileURLToPath(import.meta.url));
const REPO_ROOT = resolve(CONTRACTS_DIR, "..");

// cancun: the newest fork that solc 0.8.26, py-evm 0.12 (eth-tester), hardhat 2 and anvil all
// run; it keeps PUSH0 and MCOPY, which every one of them supports.
const SETTINGS = {
  optimizer: { enabled: true, runs: 200 },
  evmVersion: "cancun",
  outputSelection: { "*": { "*": ["abi", "evm.bytecode.object", "evm.deployedBytecode.object"] } },
};

function parseArgs(argv) {
  const options = {
    buildDir: join(CONTRACTS_DIR, "build"),
    abiDir: join(REPO_ROOT, "clients", "robocloud", "abi"),
  };
  for (let i = 0; i < argv.length; i += 2) {
    const [flag, value] = [argv[i], argv[i + 1]];
    if (value === undefined) throw new Error(`missing value for ${flag}`);
    if (flag === "--build-dir") options.buildDir = resolve(value);
    else if (flag === "--abi-dir") options.abiDir = resolve(value);
    else throw new Error(`unknown option ${flag}`);
  }
  return options;
}

function readSources() {
  const names = readdirSync(CONTRACTS_DIR).filter((f) => f.endsWith(".sol")).sort();
  if (names.length === 0) throw new Error(`no .sol files in ${CONTRACTS_DIR}`);
  return Object.fromEntries(
    names.map((name) => [name, { content: readFileSync(join(CONTRACTS_DIR, name), "utf8") }]),
  );
}

function compile(sources) {
  const input = { language: "Solidity", sources, settings: SETTINGS };
  const output = JSON.parse(solc.compile(JSON.stringify(input)));
  const diagnostics = output.errors ?? [];
  for (const d of diagnostics) process.stderr.write(`${d.formattedMessage}\n`);
  if (diagnostics.some((d) => d.severity === "error")) throw new Error("compilation failed");
  return output.contracts;
}

function writeJson(path, value) {
  writeFileSync(path, `${JSON.stringify(value, null, 2)}\n`);
}

function main() {
  const { buildDir, abiDir } = parseArgs(process.argv.slice(2));
  const sources = readSources();
  const contracts = compile(sources);
  mkdirSync(buildDir, { recursive: true });
  mkdirSync(abiDir, { recursive: true });
  const settings = { ...SETTINGS };
  delete settings.outputSelection;
  for (const sourceName of Object.keys(contracts).sort()) {
    const sourceSha256 = createHash("sha256").update(sources[sourceName].content).digest("hex");
    for (const [contractName, out] of Object.entries(contracts[sourceName]).sort()) {
      // Interfaces and abstract contracts have no bytecode and are not deployed.
      if (out.evm.bytecode.object === "") continue;
      writeJson(join(buildDir, `${contractName}.json`), {
        contractName,
        sourceName,
        sourceSha256,
        compiler: { name: "solc-js", version: solc.version() },
        settings,
        abi: out.abi,
        bytecode: `0x${out.evm.bytecode.object}`,
        deployedBytecode: `0x${out.evm.deployedBytecode.object}`,
      });
      writeJson(join(abiDir, `${contractName}.json`), { contractName, abi: out.abi });
      process.stdout.write(`${sourceName}:${contractName}\n`);
    }
  }
}

main();
