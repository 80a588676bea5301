// profuse view: the page. Loads the scene's .splat rows and camera presets from the local
// server, tints the Gaussians the server selects (pure magenta; the others grey, hidden or
// in colour) and renders with gsplat.js. Clicking the view at a preset asks the server to
// resolve the click (query by click). A scene without text prompts (info.prompts empty) is
// click only: its threshold is a cosine (info.score), and the slider re-asks for the last
// click. URL parameters: view=V (preset), prompt=NAME, threshold=T, others=grey|hide|colour.
import * as SPLAT from "/gsplat.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const state = { ready: false, frames: 0, selected: null, firstFrameMs: null, error: null };
window.profuse = state;

const info = await (await fetch("/api/scene")).json();
const base = new Uint8Array(await (await fetch("/scene.splat")).arrayBuffer());
const scene = new SPLAT.Scene();
const camera = new SPLAT.Camera();
const canvas = $("view");
// No render passes: gsplat's default FadeInPass fades splats in over 100 frames, which
// would hide a fresh selection (and take a minute on a software renderer).
const renderer = new SPLAT.WebGLRenderer(canvas, []);
const controls = new SPLAT.OrbitControls(camera, canvas);
let splat = null;
let selection = null; // Uint32Array of selected ids, or null for no selection
let lastClick = null; // {view, x, y} of the click that made the selection, or null
let preset = 0;
let atPreset = true;
let changedAt = performance.now();

function tinted() {
  const rows = new Uint8Array(base); // a copy: gsplat reads the whole buffer
  const others = $("others").value;
  if (selection === null) return rows;
  const chosen = new Uint8Array(info.gaussians);
  for (const id of selection) chosen[id] = 1;
  for (let i = 0; i < info.gaussians; i++) {
    const c = 32 * i + 24;
    if (chosen[i]) {
      rows[c] = 255; rows[c + 1] = 0; rows[c + 2] = 255;
    } else if (others === "hide") {
      rows[c + 3] = 0;
    } else if (others === "grey") {
      const g = Math.round(0.35 * (0.299 * rows[c] + 0.587 * rows[c + 1] + 0.114 * rows[c + 2]));
      rows[c] = g; rows[c + 1] = g; rows[c + 2] = g;
    }
  }
  return rows;
}

function reload() {
  if (splat) scene.removeObject(splat);
  splat = SPLAT.Loader.LoadFromArrayBuffer(tinted().buffer, scene);
  changed();
}

function changed() {
  state.ready = false;
  state.frames = 0;
  changedAt = performance.now();
}

function usePreset(v) {
  const p = info.views[v];
  preset = v;
  atPreset = true;
  $("orbit").checked = false;
  const [w, h] = p.canvas_size;
  $("window").style.width = p.width + "px";
  $("window").style.height = p.height + "px";
  canvas.style.width = w + "px";
  canvas.style.height = h + "px";
  // The canvas centre is gsplat's principal point; the server placed it at (cx, cy).
  canvas.style.left = p.canvas_origin[0] + "px";
  canvas.style.top = p.canvas_origin[1] + "px";
  camera.data.fx = p.fx;
  camera.data.fy = p.fy;
  camera.data.near = 0.01;
  camera.data.far = 1000;
  camera.position = new SPLAT.Vector3(...p.position);
  camera.rotation = new SPLAT.Quaternion(...p.rotation_xyzw);
  renderer.setSize(w, h); // re-uploads the projection (gsplat does so only on resize)
  changed();
}

async function fetchIds(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(await r.text());
  return { ids: new Uint32Array(await r.arrayBuffer()), click: r.headers.get("X-Click") };
}

async function selectPrompt() {
  const name = $("prompt").value;
  const t = $("threshold").value;
  $("threshold-value").textContent = Number(t).toFixed(2);
  try {
    if (name === "") {
      selection = null;
      lastClick = null;
      status(info.prompts.length ? "no prompt" : info.click
        ? "click the view to select (this scene has no text prompts)"
        : "no prompts: viewing Gaussians only");
    } else {
      const q = `prompt=${encodeURIComponent(name)}&threshold=${t}`;
      selection = (await fetchIds(`/api/select?${q}`)).ids;
      lastClick = null;
      $("export").href = `/api/export.ply?${q}`;
      status(`${name}: ${selection.length} of ${info.gaussians} Gaussians`);
    }
    state.selected = selection ? selection.length : null;
    reload();
  } catch (e) {
    fail(e);
  }
}

async function selectClick(ev) {
  if (!info.click) return status("query by click needs masks and proposals in the output");
  if (!atPreset) return status("choose a camera preset to click (clicks are resolved in its view)");
  // The window is the view's image: its pixel coordinates are the click's image coordinates.
  const win = $("window").getBoundingClientRect();
  await askClick({ view: preset, x: ev.clientX - win.left, y: ev.clientY - win.top });
}

async function askClick(at) {
  const { view, x: sx, y: sy } = at;
  try {
    const t = $("threshold").value;
    $("threshold-value").textContent = Number(t).toFixed(2);
    const q = `view=${view}&x=${sx}&y=${sy}&threshold=${t}`;
    const got = await fetchIds(`/api/click?${q}`);
    $("export").href = `/api/export.ply?${q}`;
    selection = got.ids;
    lastClick = at;
    $("prompt").value = "";
    state.selected = selection.length;
    status(`click (${sx.toFixed(0)}, ${sy.toFixed(0)}): ${selection.length} Gaussians\n${got.click}`);
    reload();
  } catch (e) {
    fail(e);
  }
}

function status(text) {
  $("status").textContent = text;
}

function fail(e) {
  state.error = String(e);
  status("error: " + e);
}

// Time to first frame counts until a frame shows splats (gsplat draws nothing until its
// sort worker has answered), read back before the browser composites the frame.
const gl = canvas.getContext("webgl2");
function drewSomething() {
  const px = new Uint8Array(canvas.width * canvas.height * 4);
  gl.readPixels(0, 0, canvas.width, canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
  for (let i = 3; i < px.length; i += 4) if (px[i] !== 0) return true;
  return false;
}

function frame() {
  if ($("orbit").checked) {
    atPreset = false;
    controls.update();
  }
  renderer.render(scene, camera);
  state.frames += 1;
  if (state.firstFrameMs === null && splat !== null && drewSomething()) {
    state.firstFrameMs = performance.now();
  }
  // gsplat sorts in a worker: call the view settled after a few frames and half a second.
  if (!state.ready && state.frames >= 5 && performance.now() - changedAt > 500) state.ready = true;
  requestAnimationFrame(frame);
}

for (const name of info.prompts) $("prompt").add(new Option(name, name));
info.views.forEach((v, i) => $("preset").add(new Option(`${i}: ${v.name}`, i)));
$("threshold").value = params.get("threshold") ?? info.default_threshold;
$("others").value = params.get("others") ?? "grey";
$("prompt").value = params.get("prompt") ?? "";
$("preset").value = params.get("view") ?? 0;
$("prompt").onchange = selectPrompt;
// The slider re-thresholds the current selection: the prompt's, or the last click's.
$("threshold").oninput = () => ($("prompt").value === "" && lastClick ? askClick(lastClick) : selectPrompt());
$("score-name").textContent = info.score;
if (info.prompts.length === 0) $("prompt-label").style.display = "none";
$("others").onchange = reload;
$("preset").onchange = () => usePreset(Number($("preset").value));
canvas.addEventListener("click", (ev) => { if (!$("orbit").checked) selectClick(ev); });
usePreset(Number($("preset").value));
await selectPrompt();
window.profuseSelect = async (name) => { $("prompt").value = name; await selectPrompt(); };
requestAnimationFrame(frame);
