// Build the preview page into services/preview_static/ (gitignored; the API and
// `dancegraph preview` serve it from there): one bundled script with three.js, the page
// template and the stylesheet. No hashed names: the template refers to fixed file names.
import { build } from "esbuild";
import { copyFileSync, mkdirSync, rmSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = process.env.DANCEGRAPH_PREVIEW_OUT || join(here, "..", "services", "preview_static");
rmSync(out, { recursive: true, force: true });
mkdirSync(out, { recursive: true });
await build({
  entryPoints: [join(here, "src", "main.js")],
  bundle: true,
  minify: true,
  format: "esm",
  target: "es2022",
  outfile: join(out, "preview.js"),
  legalComments: "linked",
  logLevel: "warning",
});
for (const name of ["index.html", "style.css"]) {
  copyFileSync(join(here, "src", name), join(out, name));
}
console.log(`preview page built into ${out}`);
