// Bundles our two entries (mainsail.js, fluidd.js) with the front ends' own store code, read
// from their unpacked, unmodified sources.  Usage:
//     node build.mjs MAINSAIL_ROOT FLUIDD_ROOT OUT_DIR
// Each front end's `@/x` import resolves to ROOT/src/x.  The one stub is each front end's
// src/plugins/i18n.ts (see README.md: translations give labels, never numbers, and the real
// module needs Vite: import.meta.env, a dynamic import of locale files, YAML locales).
import * as esbuild from 'esbuild'
import path from 'node:path'
import { fileURLToPath } from 'node:url'

const here = path.dirname(fileURLToPath(import.meta.url))
const [mainsailRoot, fluiddRoot, outDir] = process.argv.slice(2)
if (!outDir) {
  console.error('usage: node build.mjs MAINSAIL_ROOT FLUIDD_ROOT OUT_DIR')
  process.exit(2)
}

const I18N_STUB = `
// kestimator harness stub for src/plugins/i18n.ts: messages are keys, the locale is 'en'.
const i18n = { locale: 'en', t: (key) => key, tc: (key) => key, te: () => false }
export default i18n
export const getAllLocales = () => ['en']
export async function setAndLoadLocale () {}
`

function frontEnd (root) {
  const src = path.join(path.resolve(root), 'src')
  return {
    name: 'front-end-sources',
    setup (build) {
      build.onResolve({ filter: /^@\// }, async (args) => {
        if (args.pluginData === 'resolving') return undefined
        return build.resolve('./' + args.path.slice(2),
          { resolveDir: src, kind: args.kind, pluginData: 'resolving' })
      })
      build.onLoad({ filter: /[\\/]src[\\/]plugins[\\/]i18n\.ts$/ }, (args) => {
        if (!args.path.startsWith(src)) return undefined
        return { contents: I18N_STUB, loader: 'js' }
      })
    }
  }
}

for (const [name, root] of [['mainsail', mainsailRoot], ['fluidd', fluiddRoot]]) {
  await esbuild.build({
    entryPoints: [path.join(here, name + '.js')],
    outfile: path.join(outDir, name + '.cjs'),
    bundle: true,
    platform: 'node',
    format: 'cjs',
    target: 'node20',
    // The front ends' dependencies come from this harness's node_modules (package-lock.json).
    nodePaths: [path.join(here, 'node_modules')],
    plugins: [frontEnd(root)],
    logLevel: 'error',
    logLimit: 0
  })
}
