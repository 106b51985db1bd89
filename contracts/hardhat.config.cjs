// `npx hardhat node` for the external-node tests: a second, independent Ethereum node beside
// anvil. Chain id 1337 like the embedded chain; one account, because tests fund their own
// keys with hardhat_setBalance. Nothing here compiles: contracts are built by compile.mjs.
module.exports = {
  networks: { hardhat: { chainId: 1337, accounts: { count: 1 } } },
};
