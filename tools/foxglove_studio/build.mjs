// Assembles the static app in dist/ (git-ignored): our shell (web/), React 17's UMD builds,
// @foxglove/studio-base 1.48's prebuilt bundle (symlinked: 179 MB of chunks, workers and
// wasm, loaded relative to its index.js) and the layout converted to Studio 1.48's format.
// Any static server with HTTP Range support can serve dist/ (the remote-file data source
// reads the log by ranges); screenshot.mjs has one.
//
// Usage: node build.mjs [--layout ../../config/foxglove/glider-1.json]
import fs from "node:fs";
import path from "node:path";
import { fileURLToPath } from "node:url";

import { convertLayout } from "./convert_layout.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));
const args = process.argv.slice(2);
const layoutArg = args.indexOf("--layout");
const layoutPath =
  layoutArg >= 0 ? path.resolve(args[layoutArg + 1]) : path.join(here, "../../config/foxglove/glider-1.json");

const dist = path.join(here, "dist");
const modules = path.join(here, "node_modules");
const studioAssets = path.join(modules, "@foxglove/studio-base/assets");
if (!fs.existsSync(path.join(studioAssets, "index.js"))) {
  throw new Error(`${studioAssets}/index.js missing: run npm ci in ${here} first`);
}

fs.rmSync(dist, { recursive: true, force: true });
fs.mkdirSync(path.join(dist, "vendor"), { recursive: true });
for (const name of ["index.html", "entry.js"]) {
  fs.copyFileSync(path.join(here, "web", name), path.join(dist, name));
}
fs.copyFileSync(path.join(modules, "react/umd/react.production.min.js"), path.join(dist, "vendor/react.production.min.js"));
fs.copyFileSync(
  path.join(modules, "react-dom/umd/react-dom.production.min.js"),
  path.join(dist, "vendor/react-dom.production.min.js"),
);
fs.symlinkSync(studioAssets, path.join(dist, "studio-base"), "dir");

const { data, dropped } = convertLayout(JSON.parse(fs.readFileSync(layoutPath, "utf8")));
fs.writeFileSync(path.join(dist, "layout.json"), JSON.stringify(data, null, 2) + "\n");
console.log(`dist/ built: layout ${path.relative(process.cwd(), layoutPath)}, ${Object.keys(data.configById).length} panels`);
if (dropped.length > 0) console.log(`options Studio 1.48 does not have, dropped: ${dropped.join(", ")}`);
