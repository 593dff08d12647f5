// Opens a log in the Studio build (dist/, see build.mjs) with our layout, in headless
// Debian chromium driven by playwright-core, and writes a screenshot.
//
// Usage: node screenshot.mjs --log COPY.mcap --out PNG [--time RFC3339] [--width 1600 --height 1000]
//
// Everything is on 127.0.0.1: one server (serve.mjs) holds the app and the log, and every
// request to another host is refused and reported (the app needs no internet). The app
// opens the log through its remote-file data source and the layout by id, both from the URL
// (?ds=remote-file&ds.url=...&layoutId=glider-1&time=...), the way Studio's own deep links do.
// Readiness: the log's topics are listed, then the panels are redrawn until their pixels
// stop changing (Studio loads the plotted topics of the whole log in blocks, in a worker,
// and has no signal for it in the page), up to --timeout seconds.
import fs from "node:fs";
import os from "node:os";
import path from "node:path";
import { fileURLToPath } from "node:url";

import { chromium } from "playwright-core";

import { serve } from "./serve.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));

function parseArgs(argv) {
  const args = { width: 1600, height: 1000, timeout: 300, chromium: "/usr/bin/chromium" };
  for (let i = 0; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, "");
    if (!(key in args) && !["log", "out", "time"].includes(key)) throw new Error(`unknown option ${argv[i]}`);
    args[key] = argv[i + 1];
  }
  if (!args.log || !args.out) throw new Error("usage: node screenshot.mjs --log LOG.mcap --out PNG [--time RFC3339]");
  return args;
}

async function main() {
  const args = parseArgs(process.argv.slice(2));
  const dist = path.join(here, "dist");
  if (!fs.existsSync(path.join(dist, "layout.json"))) throw new Error("dist/ missing: run node build.mjs first");
  const logPath = path.resolve(args.log);
  const { server, url } = await serve(dist, logPath);
  const userDataDir = fs.mkdtempSync(path.join(os.tmpdir(), "studio-profile-"));
  const refused = [];
  const problems = [];
  let context;
  try {
    context = await chromium.launchPersistentContext(userDataDir, {
      executablePath: args.chromium,
      headless: true,
      args: [
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
      ],
      viewport: { width: Number(args.width), height: Number(args.height) },
      timezoneId: "UTC",
      locale: "en-US",
    });
    await context.route("**/*", (route) => {
      const u = new URL(route.request().url());
      if (u.hostname === "127.0.0.1" || u.protocol === "data:" || u.protocol === "blob:") return route.continue();
      refused.push(u.href);
      return route.abort();
    });
    const page = context.pages()[0] ?? (await context.newPage());
    page.on("pageerror", (e) => problems.push(`page error: ${e.message}`));
    page.on("console", (m) => {
      if (m.type() === "error" && /Player problem/.test(m.text())) problems.push(m.text().slice(0, 300));
    });

    const params = new URLSearchParams({ ds: "remote-file", "ds.url": `${url}log/${path.basename(logPath)}`, layoutId: "glider-1" });
    if (args.time) params.set("time", args.time);
    await page.goto(`${url}?${params}`);
    const timeoutMs = Number(args.timeout) * 1000;
    // The data source is open once the sidebar lists its topics.
    await page.getByText("glider/1/telemetry", { exact: true }).first().waitFor({ timeout: timeoutMs });
    // Close the sidebar (its first button toggles it) so the panels get the width.
    await page.locator('[data-testid="panel-mouseenter-container Plot!glider1"]').waitFor({ timeout: timeoutMs });
    const panels = page.locator(".mosaic").last();
    const before = await panels.boundingBox();
    await page.locator("[data-sidebar-key]").first().click().catch(() => {});
    const after = await panels.boundingBox();
    if (before && after && after.width <= before.width) {
      process.stderr.write("note: the sidebar did not close\n");
    }

    // Redraw until stable: the same pixels in `stableFor` screenshots in a row.
    const stableFor = 4;
    const deadline = Date.now() + timeoutMs;
    let last;
    let same = 0;
    let shots = 0;
    while (same < stableFor - 1) {
      if (Date.now() > deadline) throw new Error(`the panels were still changing after ${args.timeout} s`);
      await page.waitForTimeout(1000);
      const shot = await panels.screenshot();
      shots += 1;
      same = last !== undefined && shot.equals(last) ? same + 1 : 0;
      last = shot;
    }
    fs.mkdirSync(path.dirname(path.resolve(args.out)), { recursive: true });
    await page.screenshot({ path: args.out });
    console.log(`${args.out}: ${args.width}x${args.height}, panels stable after ${shots} looks`);
    if (problems.length > 0) console.log(`Studio reported ${problems.length} problem(s):\n  ${[...new Set(problems)].join("\n  ")}`);
    if (refused.length > 0) console.log(`refused ${refused.length} request(s) off loopback:\n  ${[...new Set(refused)].join("\n  ")}`);
  } finally {
    await context?.close();
    server.close();
    fs.rmSync(userDataDir, { recursive: true, force: true });
  }
}

main().catch((err) => {
  console.error(err);
  process.exit(1);
});
