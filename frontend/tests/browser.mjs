// Drive the preview page in real headless Chromium (Debian's /usr/bin/chromium through
// playwright-core) and print what was observed as one JSON object; the pytest test
// (tests/services/test_preview_browser.py) makes the assertions.
//
//   node tests/browser.mjs URL SCREENSHOT.png [SWITCH_TIME_S]
//
// Observed: console errors, page errors and failed requests; non-background canvas pixels;
// the pose at two seek times; the clock and pose after real playback; the pose after switching
// the alternative at SWITCH_TIME_S; a couple's two skeletons and both poses at three times; the
// pose on the user's rig where the page offers it; the cost breakdown shown after clicking a bar.
import { chromium } from "playwright-core";

const [url, screenshot, switchTimeArg] = process.argv.slice(2);
if (!url || !screenshot) {
  console.error("usage: node tests/browser.mjs URL SCREENSHOT.png [SWITCH_TIME_S]");
  process.exit(2);
}
const switchTime = Number(switchTimeArg || 1.0);
const executablePath = process.env.CHROMIUM || "/usr/bin/chromium";

// launch() gives Chromium a fresh, empty profile of its own
const browser = await chromium.launch({
  executablePath,
  headless: true,
  args: [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    // WebGL on the CPU (no GPU here), and sound without a user gesture
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--autoplay-policy=no-user-gesture-required",
  ],
});
const out = { console_errors: [], page_errors: [], failed_requests: [] };
try {
  const page = await browser.newPage({ viewport: { width: 1200, height: 820 } });
  page.on("console", (msg) => {
    if (msg.type() === "error") out.console_errors.push(msg.text());
  });
  page.on("pageerror", (err) => out.page_errors.push(String(err)));
  page.on("requestfailed", (req) => {
    // a media element aborting its own range request when seeking is not a failure
    if (req.resourceType() !== "media") out.failed_requests.push(`${req.url()} ${req.failure()?.errorText}`);
  });
  page.on("response", (resp) => {
    if (resp.status() >= 400) out.failed_requests.push(`${resp.url()} ${resp.status()}`);
  });
  await page.goto(url, { waitUntil: "load" });
  await page.waitForFunction(() => window.__preview && (window.__preview.ready || window.__preview.error), null, {
    timeout: 30000,
  });
  out.error = await page.evaluate(() => window.__preview.error);
  out.alternatives = await page.evaluate(() => window.__preview.alternatives);
  // media metadata loaded, so seeking works
  await page.waitForFunction(() => document.getElementById("audio").readyState >= 1, null, { timeout: 15000 });
  const frames = () => page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const poseAt = async (t) => {
    await page.evaluate((s) => window.__preview.seek(s), t);
    await page.waitForFunction((s) => Math.abs(window.__preview.time - s) < 0.05, t, { timeout: 10000 });
    await frames();
    return page.evaluate(() => ({ time: window.__preview.time, bar: window.__preview.bar, pose: window.__preview.pose() }));
  };
  out.seek_a = await poseAt(0.5);
  out.seek_b = await poseAt(switchTime);
  // a couple: both skeletons in the scene, the lead's and the follow's pose at a few times
  out.couple = null;
  if (await page.evaluate(() => window.__preview.followPose() !== null)) {
    const at = [];
    for (const t of [0.5, switchTime, 2 * switchTime]) {
      const seen = await poseAt(t);
      at.push({ ...seen, follow: await page.evaluate(() => window.__preview.followPose()) });
    }
    out.couple = { skeletons: await page.evaluate(() => window.__preview.skeletons), at };
  }
  // non-background pixels of the WebGL canvas (preserveDrawingBuffer keeps the last frame)
  out.canvas = await page.evaluate(() => {
    const src = document.querySelector("#view canvas");
    const c = document.createElement("canvas");
    c.width = src.width;
    c.height = src.height;
    const ctx = c.getContext("2d");
    ctx.drawImage(src, 0, 0);
    const data = ctx.getImageData(0, 0, c.width, c.height).data;
    let differing = 0;
    const colours = new Set();
    for (let i = 0; i < data.length; i += 4) {
      const [r, g, b] = [data[i], data[i + 1], data[i + 2]];
      if (Math.abs(r - 0x15) + Math.abs(g - 0x17) + Math.abs(b - 0x1c) > 12) differing++;
      if (colours.size < 5000) colours.add((r << 16) | (g << 8) | b);
    }
    return { width: c.width, height: c.height, non_background: differing, colours: colours.size };
  });
  // real playback: the audio clock runs and the drawn pose follows it
  await page.evaluate(() => window.__preview.seek(0.2));
  await frames();
  const before = await page.evaluate(() => ({ time: window.__preview.time, pose: window.__preview.pose() }));
  out.play_error = await page.evaluate(() =>
    window.__preview.play().then(
      () => null,
      (e) => String(e),
    ),
  );
  // the audio clock must move on by itself (no seeking); generous timeout for a loaded machine
  await page
    .waitForFunction((t0) => window.__preview.time > t0 + 0.8, before.time, { timeout: 20000 })
    .catch(() => null);
  await frames();
  const after = await page.evaluate(() => ({ time: window.__preview.time, pose: window.__preview.pose() }));
  await page.evaluate(() => window.__preview.pause());
  out.play = { before, after };
  // switching the alternative at the same time changes the drawn pose
  const atSwitch = await poseAt(switchTime);
  await page.evaluate(() => window.__preview.setAlternative(1));
  await frames();
  out.switch = {
    before: atSwitch,
    after: await page.evaluate(() => ({
      alternative: window.__preview.alternative,
      selected: document.getElementById("alternative").value,
      pose: window.__preview.pose(),
    })),
  };
  // a rig with a mesh: the page opens on the skinned character, the skeleton one click away
  out.character = null;
  if (await page.evaluate(() => !document.getElementById("view-toggle").hidden)) {
    await poseAt(switchTime);
    const shown = await page.evaluate(() => ({ view: window.__preview.view, box: window.__preview.character() }));
    await page.screenshot({ path: screenshot.replace(/\.png$/, "-character.png") });
    await page.click("#view-toggle");
    await page.waitForFunction(() => window.__preview.character() === null, null, { timeout: 20000 });
    await frames();
    const toggled = await page.evaluate(() => ({ view: window.__preview.view, box: window.__preview.character() }));
    out.character = { shown, toggled, screenshot: screenshot.replace(/\.png$/, "-character.png") };
    const n = await page.evaluate(() => window.__preview.pose().length);
    await page.selectOption("#skeleton", "library");
    await page.waitForFunction((m) => window.__preview.pose().length !== m, n, { timeout: 20000 });
  }
  // a result on the user's rig: the Skeleton select switches to the rig's joints
  out.rig = null;
  if (await page.evaluate(() => !document.getElementById("skeleton-label").hidden)) {
    const before = await page.evaluate(() => window.__preview.pose().length);
    await page.selectOption("#skeleton", "rig");
    await page.waitForFunction((n) => window.__preview.pose().length !== n, before, { timeout: 20000 });
    await frames();
    out.rig = { before, after: await page.evaluate(() => window.__preview.pose()) };
    await page.selectOption("#skeleton", "library");
    await page.waitForFunction((n) => window.__preview.pose().length === n, before, { timeout: 20000 });
  }
  // clicking a bar shows its cost breakdown
  await page.click('#bars .bar[data-bar="1"]');
  out.breakdown = await page.evaluate(() => {
    const table = document.getElementById("breakdown");
    return {
      text: document.getElementById("details").innerText,
      rows: table ? Array.from(table.querySelectorAll("tr")).map((tr) => tr.innerText) : [],
    };
  });
  await poseAt(switchTime);
  out.current_bars = await page.evaluate(() => Array.from(document.querySelectorAll("#bars .bar.current")).map((e) => Number(e.dataset.bar)));
  await page.screenshot({ path: screenshot });
  out.screenshot = screenshot;
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
