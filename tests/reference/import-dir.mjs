// The root CID js-ipfs-unixfs's importer gives a directory tree, as `ipfs add -r` would.
// Usage: node import-dir.mjs DIR [cidVersion] [rawLeaves] [profile]
import { readdir, readFile } from 'node:fs/promises'
import { join, relative, basename } from 'node:path'
import { importer } from 'ipfs-unixfs-importer'
import { MemoryBlockstore } from 'blockstore-core/memory'

const [root, cidVersion = '1', rawLeaves = 'true', profile] = process.argv.slice(2)

async function * walk (dir) {
  yield { path: relative(join(root, '..'), dir) }
  for (const entry of (await readdir(dir, { withFileTypes: true })).sort((a, b) => a.name < b.name ? -1 : 1)) {
    const path = join(dir, entry.name)
    if (entry.isDirectory()) {
      yield * walk(path)
    } else {
      yield { path: relative(join(root, '..'), path), content: await readFile(path) }
    }
  }
}

const options = profile
  ? { profile }
  : { cidVersion: Number(cidVersion), rawLeaves: rawLeaves === 'true' }
let last
for await (const entry of importer(walk(root), new MemoryBlockstore(), options)) {
  if (entry.path === basename(root)) last = entry
}
console.log(last.cid.toString())
