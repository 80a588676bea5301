// Drives `profuse view` in headless Chromium (the system browser, WebGL through
// SwiftShader) with playwright-core.
//
//   node drive.mjs shots URL OUT_DIR PROMPT2   screenshot the view window at URL (which
//                                              names view and prompt), then again after
//                                              choosing PROMPT2: OUT_DIR/first.png, second.png
//   node drive.mjs bench URL [SECONDS]         time to first frame and frames per second
//
// Prints one JSON object on stdout. CHROMIUM overrides the browser path.
import { chromium } from "playwright-core";

const [mode, url, ...rest] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  args: ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--no-sandbox"],
});
try {
  const page = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(String(e)));
  page.on("console", (m) => m.type() === "error" && errors.push(m.text()));
  // An element screenshot waits for two stable animation frames, which a software
  // renderer may not give in time: clip a page screenshot to the view window instead.
  const shoot = async (path) => {
    const box = await page.locator("#window").boundingBox();
    await page.screenshot({ path, clip: box });
  };
  await page.goto(url);
  const settled = async () => {
    await page.waitForFunction(() => window.profuse && (window.profuse.ready || window.profuse.error),
      null, { timeout: 120000, polling: 100 });
    const s = await page.evaluate(() => window.profuse);
    if (s.error) throw new Error(s.error + " " + errors.join("; "));
    return s;
  };
  if (mode === "shots") {
    const [outDir, prompt2] = rest;
    const first = await settled();
    await shoot(`${outDir}/first.png`);
    await page.evaluate((p) => window.profuseSelect(p), prompt2);
    const second = await settled();
    await shoot(`${outDir}/second.png`);
    console.log(JSON.stringify({ first_selected: first.selected, second_selected: second.selected, errors }));
  } else if (mode === "bench") {
    const seconds = Number(rest[0] ?? 5);
    await page.waitForFunction(() => window.profuse && window.profuse.firstFrameMs !== null,
      null, { timeout: 300000, polling: 50 });
    const ttff = await page.evaluate(() => window.profuse.firstFrameMs);
    const f0 = await page.evaluate(() => [window.profuse.frames, performance.now()]);
    await page.waitForTimeout(seconds * 1000);
    const f1 = await page.evaluate(() => [window.profuse.frames, performance.now()]);
    const fps = (f1[0] - f0[0]) / ((f1[1] - f0[1]) / 1000);
    const renderer = await page.evaluate(() => {
      const gl = document.createElement("canvas").getContext("webgl2");
      const ext = gl && gl.getExtension("WEBGL_debug_renderer_info");
      return ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : null;
    });
    console.log(JSON.stringify({ time_to_first_frame_ms: ttff, fps, seconds, renderer, errors }));
  } else {
    throw new Error(`unknown mode ${mode}`);
  }
} finally {
  await browser.close();
}
