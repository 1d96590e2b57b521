// npm run build: bundle src/ with three into ../dejaview/server/static (what the Python package
// ships), and copy iwer's browser build into ../tests/web/assets for the WebXR test.
// DEJAVIEW_WEB_OUT=DIR builds into DIR/static and DIR/assets instead (scripts/check-web compares
// that build with the committed files).
import { build } from 'esbuild';
import { copyFileSync, mkdirSync, rmSync } from 'node:fs';

const root = process.env.DEJAVIEW_WEB_OUT;
const out = root ? `${root}/static/` : new URL('../dejaview/server/static/', import.meta.url).pathname;
rmSync(out, { recursive: true, force: true });
mkdirSync(out, { recursive: true });
await build({
  entryPoints: ['src/main.js'],
  bundle: true,
  format: 'esm',
  minify: true,
  sourcemap: false,
  target: ['es2022'],
  outfile: `${out}app.js`,
  legalComments: 'eof',
  logLevel: 'info',
});
for (const name of ['index.html', 'style.css']) copyFileSync(`public/${name}`, `${out}${name}`);

const assets = root ? `${root}/assets/` : new URL('../tests/web/assets/', import.meta.url).pathname;
mkdirSync(assets, { recursive: true });
copyFileSync('node_modules/iwer/build/iwer.min.js', `${assets}iwer.min.js`);
copyFileSync('node_modules/iwer/LICENSE', `${assets}iwer.LICENSE`);
