// The preview page: the song's <audio> element is the clock; every animation frame samples the
// chosen alternative's pose at audio.currentTime and draws the skeleton as capsules on a floor
// grid with the stage bounds (a couple: the lead and the follow, config.follow_poses, in one
// world frame, each in its own colours). The timeline under the view shows phrases, bars and the chosen
// node per bar; clicking a bar shows its cost breakdown. Data URLs come from the JSON config the
// server puts into the page (API: signed ?token= URLs; `dancegraph preview`: local paths).
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const config = JSON.parse(document.getElementById("preview-config").textContent);
const $ = (id) => document.getElementById(id);
const audio = $("audio");
const statusEl = $("status");

const state = {
  ready: false,
  error: null,
  timeline: null,
  tracks: {}, // per pose URL: Promise of {fps, frames, joints, parents, positions: Float32Array (m)}
  skeleton: "library", // or "rig" where the job was also written on the user's rig
  view: "character", // on a rig with a mesh: the skinned character, or "skeleton" (capsules)
  models: {}, // per GLB URL: Promise of {root, mixer, skinned} (alternatives/<k>.rig.glb)
  model: null, // the character drawn now, or null
  track: null,
  alternative: 0,
  bar: -1,
  selectedBar: -1,
  pose: null, // Float32Array J·3 of the pose last drawn (metres)
  followTrack: null, // a couple's follow (config.follow_poses), drawn beside the lead
  followPose: null,
};

function setStatus(text, isError = false) {
  statusEl.textContent = text;
  statusEl.classList.toggle("error", isError);
}

function fail(err) {
  state.error = String(err && err.message ? err.message : err);
  setStatus(state.error, true);
}

async function getJson(url) {
  const resp = await fetch(url);
  if (!resp.ok) {
    let detail = resp.statusText;
    try {
      const body = await resp.json();
      detail = body.detail || body.code || detail;
    } catch {
      // not JSON: keep the status text
    }
    throw new Error(`${url.split("?")[0]}: ${resp.status} ${detail}`);
  }
  return resp.json();
}

function fmtTime(t) {
  const m = Math.floor(t / 60);
  const s = t - m * 60;
  return `${m}:${s.toFixed(1).padStart(4, "0")}`;
}

// --- scene -------------------------------------------------------------------------------

const view = $("view");
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
view.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x15171c);
const camera = new THREE.PerspectiveCamera(45, 1, 0.05, 200);
camera.position.set(2.6, 2.0, 4.2);
const controls = new OrbitControls(camera, renderer.domElement);
controls.target.set(0, 0.8, 0);
controls.update();

// Framing: the camera looks at the box the dancer covers over the whole first track (every
// joint, every frame, a margin around, down to the floor) from the front, a little right and
// above, at the least distance that keeps all of the box in view, so the skeleton fills the view
// wherever it dances on the stage. Refitted on resize until the user moves the camera.
const VIEW_DIR = new THREE.Vector3(0.35, 0.26, 1).normalize();
let framedBox = null;
let userMoved = false;
controls.addEventListener("start", () => (userMoved = true));

function trackBox(track, margin = 0.15) {
  const box = new THREE.Box3();
  const p = track.positions;
  const v = new THREE.Vector3();
  for (let i = 0; i < p.length; i += 3) box.expandByPoint(v.set(p[i], p[i + 1], p[i + 2]));
  box.min.x -= margin;
  box.min.z -= margin;
  box.max.x += margin;
  box.max.z += margin;
  box.min.y = Math.min(box.min.y, 0);
  box.max.y += 0.1;
  return box;
}

function frameBox(box) {
  const target = box.getCenter(new THREE.Vector3());
  const right = new THREE.Vector3().crossVectors(new THREE.Vector3(0, 1, 0), VIEW_DIR).normalize();
  const up = new THREE.Vector3().crossVectors(VIEW_DIR, right);
  const tanV = Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  const tanH = tanV * camera.aspect;
  const c = new THREE.Vector3();
  let distance = 0;
  for (const x of [box.min.x, box.max.x]) {
    for (const y of [box.min.y, box.max.y]) {
      for (const z of [box.min.z, box.max.z]) {
        c.set(x, y, z).sub(target);
        // camera at target + distance·VIEW_DIR: this corner's depth is distance − c·VIEW_DIR
        const depth = c.dot(VIEW_DIR);
        distance = Math.max(
          distance,
          depth + Math.abs(c.dot(right)) / tanH,
          depth + Math.abs(c.dot(up)) / tanV,
        );
      }
    }
  }
  camera.position.copy(target).addScaledVector(VIEW_DIR, distance * 1.05);
  controls.target.copy(target);
  controls.update();
}
scene.add(new THREE.HemisphereLight(0xffffff, 0x404050, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.4);
sun.position.set(3, 6, 4);
scene.add(sun);
scene.add(new THREE.GridHelper(20, 40, 0x59627a, 0x2f3542));

// A drawn skeleton: bones, an InstancedMesh of unit cylinders, one per (joint, parent) pair;
// joints, one of spheres, one per joint. The lead (or a solo dancer) and a couple's follow.
function figure(boneColor, jointColor) {
  return {
    boneMaterial: new THREE.MeshStandardMaterial({ color: boneColor, roughness: 0.5 }),
    jointMaterial: new THREE.MeshStandardMaterial({ color: jointColor, roughness: 0.4 }),
    bones: null,
    joints: null,
  };
}
const lead = figure(0x79c0ff, 0xffa657);
const follow = figure(0xf778ba, 0xd2a8ff);
let stageLines = null;

function resize() {
  const w = view.clientWidth || 640;
  const h = view.clientHeight || 360;
  renderer.setSize(w, h, false);
  renderer.domElement.style.width = `${w}px`;
  renderer.domElement.style.height = `${h}px`;
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  if (framedBox && !userMoved) frameBox(framedBox);
}
window.addEventListener("resize", resize);
resize();

function drawStage(stage) {
  if (stageLines) scene.remove(stageLines);
  stageLines = null;
  if (!stage || !stage.x || !stage.z) return;
  const [x0, x1] = stage.x;
  const [z0, z1] = stage.z;
  const y = 0.01;
  const geometry = new THREE.BufferGeometry().setFromPoints([
    new THREE.Vector3(x0, y, z0),
    new THREE.Vector3(x1, y, z0),
    new THREE.Vector3(x1, y, z1),
    new THREE.Vector3(x0, y, z1),
  ]);
  stageLines = new THREE.LineLoop(geometry, new THREE.LineBasicMaterial({ color: 0xff7b72 }));
  scene.add(stageLines);
}

function removeSkeleton(fig) {
  for (const mesh of [fig.bones, fig.joints]) {
    if (mesh) {
      scene.remove(mesh);
      mesh.dispose();
    }
  }
  fig.bones = fig.joints = null;
}

function buildSkeleton(fig, track) {
  removeSkeleton(fig);
  const nBones = track.parents.filter((p) => p >= 0).length;
  fig.bones = new THREE.InstancedMesh(new THREE.CylinderGeometry(1, 1, 1, 10), fig.boneMaterial, nBones);
  fig.joints = new THREE.InstancedMesh(new THREE.SphereGeometry(1, 12, 8), fig.jointMaterial, track.parents.length);
  for (const mesh of [fig.bones, fig.joints]) {
    mesh.instanceMatrix.setUsage(THREE.DynamicDrawUsage);
    mesh.frustumCulled = false;
    scene.add(mesh);
  }
}

const _a = new THREE.Vector3();
const _b = new THREE.Vector3();
const _dir = new THREE.Vector3();
const _up = new THREE.Vector3(0, 1, 0);
const _q = new THREE.Quaternion();
const _s = new THREE.Vector3();
const _m = new THREE.Matrix4();
const _one = new THREE.Quaternion();

// The pose at time t (s): linear blend of the two frames around t·fps (held at both ends).
// Writes into `out` when it has the right length (no garbage per animation frame).
function samplePose(track, t, out = null) {
  const J = track.joints.length;
  if (!out || out.length !== J * 3) out = new Float32Array(J * 3);
  const f = Math.min(Math.max(t * track.fps, 0), track.frames - 1);
  const f0 = Math.floor(f);
  const f1 = Math.min(f0 + 1, track.frames - 1);
  const w = f - f0;
  const p = track.positions;
  const o0 = f0 * J * 3;
  const o1 = f1 * J * 3;
  for (let i = 0; i < J * 3; i++) out[i] = p[o0 + i] * (1 - w) + p[o1 + i] * w;
  return out;
}

function drawPose(fig, track, pose) {
  const { bones, joints } = fig;
  let k = 0;
  for (let j = 0; j < track.parents.length; j++) {
    _a.set(pose[j * 3], pose[j * 3 + 1], pose[j * 3 + 2]);
    const r = track.joints[j].endsWith("_end") ? 0.018 : 0.03;
    _m.compose(_a, _one, _s.set(r, r, r));
    joints.setMatrixAt(j, _m);
    const p = track.parents[j];
    if (p < 0) continue;
    _b.set(pose[p * 3], pose[p * 3 + 1], pose[p * 3 + 2]);
    _dir.subVectors(_a, _b);
    const len = _dir.length();
    if (len > 1e-6) _q.setFromUnitVectors(_up, _dir.multiplyScalar(1 / len));
    else _q.identity();
    _m.compose(_a.add(_b).multiplyScalar(0.5), _q, _s.set(0.022, len, 0.022));
    bones.setMatrixAt(k++, _m);
  }
  bones.instanceMatrix.needsUpdate = true;
  joints.instanceMatrix.needsUpdate = true;
}

// --- timeline ------------------------------------------------------------------------------

function duration() {
  const d = audio.duration;
  return Number.isFinite(d) && d > 0 ? d : state.timeline.duration_s;
}

function buildTimeline() {
  const tl = state.timeline;
  const total = tl.duration_s;
  const pct = (s) => `${(100 * s) / total}%`;
  const phrases = $("phrases");
  phrases.replaceChildren();
  (tl.phrases || []).forEach((ph, i) => {
    const first = tl.bars[ph.start_bar];
    const last = tl.bars[Math.min(ph.end_bar, tl.bars.length) - 1];
    if (!first || !last) return;
    const el = document.createElement("div");
    el.className = i % 2 ? "phrase alt" : "phrase";
    el.style.left = pct(first.start_s);
    el.style.width = pct(last.end_s - first.start_s);
    el.textContent = ph.occurrence ? `${ph.label}${ph.occurrence + 1}` : ph.label;
    el.title = `phrase ${ph.label}, bars ${ph.start_bar}–${ph.end_bar - 1}`;
    phrases.appendChild(el);
  });
  const bars = $("bars");
  bars.replaceChildren();
  tl.bars.forEach((bar, b) => {
    const el = document.createElement("div");
    el.className = "bar";
    el.dataset.bar = String(b);
    el.style.left = pct(bar.start_s);
    el.style.width = pct(bar.end_s - bar.start_s);
    el.innerHTML = `<span>${b}</span><span class="node"></span>`;
    el.addEventListener("click", () => selectBar(b));
    bars.appendChild(el);
  });
  labelNodes();
}

function altBars() {
  const alt = state.timeline.alternatives[state.alternative];
  return (alt && alt.bars) || [];
}

function labelNodes() {
  const chosen = altBars();
  for (const el of $("bars").children) {
    const entry = chosen[Number(el.dataset.bar)];
    const node = entry ? entry.node : "";
    el.querySelector(".node").textContent = node;
    el.title = `bar ${el.dataset.bar}: ${node}`;
  }
  if (state.selectedBar >= 0) selectBar(state.selectedBar);
}

function cell(tag, text) {
  const el = document.createElement(tag);
  el.textContent = text;
  return el;
}

function selectBar(b) {
  state.selectedBar = b;
  for (const el of $("bars").children) el.classList.toggle("selected", Number(el.dataset.bar) === b);
  const bar = state.timeline.bars[b];
  const entry = altBars()[b] || {};
  const details = $("details");
  details.replaceChildren();
  const head = cell("p", "");
  head.append(cell("strong", `Bar ${b}`), ` ${fmtTime(bar.start_s)}–${fmtTime(bar.end_s)} · node `);
  head.append(cell("code", entry.node || "?"));
  const src = entry.source || {};
  if (src.take) {
    const frames = src.frames ? ` frames ${src.frames[0]}–${src.frames[1]}` : "";
    const aug = src.augmentation ? ` (${src.augmentation})` : "";
    head.append(` · from ${src.take} bar ${src.bar}${frames}${aug}`);
  }
  if (entry.motif !== undefined) head.append(` · motif ${entry.motif}`);
  const jump = cell("button", "Jump to bar");
  jump.type = "button";
  jump.addEventListener("click", () => seek(bar.start_s));
  head.append(" ", jump);
  details.appendChild(head);
  const cost = entry.cost || {};
  const table = document.createElement("table");
  table.id = "breakdown";
  const header = document.createElement("tr");
  header.append(cell("th", "cost term"), cell("th", "value"));
  table.appendChild(header);
  let total = 0;
  for (const [term, value] of Object.entries(cost)) {
    const row = document.createElement("tr");
    const shown = typeof value === "number" ? value.toFixed(4) : JSON.stringify(value);
    if (typeof value === "number") total += value;
    row.append(cell("td", term), cell("td", shown));
    table.appendChild(row);
  }
  const sum = document.createElement("tr");
  sum.append(cell("th", "sum"), cell("th", total.toFixed(4)));
  table.appendChild(sum);
  details.appendChild(Object.keys(cost).length ? table : cell("p", "no cost breakdown recorded for this bar"));
}

function barAt(t) {
  const bars = state.timeline.bars;
  for (let b = 0; b < bars.length; b++) if (t >= bars[b].start_s && t < bars[b].end_s) return b;
  return -1;
}

// --- playback ------------------------------------------------------------------------------

function seek(t) {
  audio.currentTime = Math.min(Math.max(t, 0), duration());
}

// the skeleton shown: the motion library's, or the user's rig (config.rig_poses, spec output.rig)
function poseUrl(k) {
  return state.skeleton === "rig" && config.rig_poses ? config.rig_poses[k] : config.poses[k];
}

async function loadTrack(k, url = poseUrl(k)) {
  if (!state.tracks[url]) {
    state.tracks[url] = getJson(url).then((raw) => {
      const scale = raw.unit === "mm" ? 0.001 : 1;
      return { ...raw, positions: Float32Array.from(raw.positions, (v) => v * scale) };
    });
  }
  return state.tracks[url];
}

function sameSkeleton(a, b) {
  return a && b && a.joints.length === b.joints.length && a.joints.every((n, i) => n === b.joints[i]);
}

// the dance on the user's own character (config.rig_models: each alternative's .rig.glb)
function loadModel(k) {
  const url = config.rig_models[k];
  if (!state.models[url]) {
    state.models[url] = new GLTFLoader().loadAsync(url).then((gltf) => {
      let skinned = false;
      gltf.scene.traverse((o) => {
        if (o.isSkinnedMesh) {
          skinned = true;
          o.frustumCulled = false;
          o.material = new THREE.MeshStandardMaterial({ color: 0xc8a27a, roughness: 0.7 });
        }
      });
      const mixer = new THREE.AnimationMixer(gltf.scene);
      if (gltf.animations.length) mixer.clipAction(gltf.animations[0]).play();
      return { root: gltf.scene, mixer, skinned };
    });
  }
  return state.models[url];
}

// the character in view where the rig has a mesh and the character view is chosen
async function showModel(k) {
  let model = null;
  if (state.skeleton === "rig" && config.rig_models) {
    const loaded = await loadModel(k);
    $("view-toggle").hidden = !loaded.skinned; // a rig without a mesh has only its skeleton
    if (loaded.skinned && state.view === "character") model = loaded;
  }
  if (state.model && state.model !== model) scene.remove(state.model.root);
  if (model && state.model !== model) scene.add(model.root);
  state.model = model;
  for (const mesh of [lead.bones, lead.joints]) if (mesh) mesh.visible = !model;
  $("view-toggle").textContent = model ? "Skeleton view" : "Character view";
}

async function setAlternative(k) {
  k = Number(k);
  const track = await loadTrack(k);
  // a couple's follow, on the library skeleton (the lead's rig view is a solo job's)
  const second = config.follow_poses ? await loadTrack(k, config.follow_poses[k]) : null;
  state.alternative = k;
  $("alternative").value = String(k);
  if (!sameSkeleton(state.track, track)) buildSkeleton(lead, track);
  if (!second) removeSkeleton(follow);
  else if (!sameSkeleton(state.followTrack, second) || !follow.bones) buildSkeleton(follow, second);
  if (!framedBox) {
    framedBox = trackBox(track);
    if (second) framedBox.union(trackBox(second));
    frameBox(framedBox);
  }
  state.track = track;
  state.followTrack = second;
  labelNodes();
  await showModel(k);
  return k;
}

function frame() {
  if (state.track) {
    const t = audio.currentTime;
    state.pose = samplePose(state.track, t, state.pose);
    drawPose(lead, state.track, state.pose);
    if (state.followTrack) {
      state.followPose = samplePose(state.followTrack, t, state.followPose);
      drawPose(follow, state.followTrack, state.followPose);
    }
    if (state.model) state.model.mixer.setTime(t);
    const b = barAt(t);
    if (b !== state.bar) {
      for (const el of $("bars").children) el.classList.toggle("current", Number(el.dataset.bar) === b);
      state.bar = b;
    }
    const d = duration();
    $("cursor").style.left = `${(100 * t) / state.timeline.duration_s}%`;
    const seekEl = $("seek");
    if (document.activeElement !== seekEl) seekEl.value = String(t);
    seekEl.max = String(d);
    $("clock").textContent = `${fmtTime(t)} / ${fmtTime(d)}`;
  }
  renderer.render(scene, camera);
  requestAnimationFrame(frame);
}

function wireControls() {
  const play = $("play");
  play.addEventListener("click", () => (audio.paused ? audio.play() : audio.pause()));
  audio.addEventListener("play", () => (play.textContent = "Pause"));
  audio.addEventListener("pause", () => (play.textContent = "Play"));
  audio.addEventListener("ended", () => (play.textContent = "Play"));
  $("seek").addEventListener("input", (e) => seek(Number(e.target.value)));
  $("alternative").addEventListener("change", (e) => setAlternative(e.target.value).catch(fail));
  if (config.rig_models) {
    const toggle = $("view-toggle");
    toggle.hidden = false;
    toggle.addEventListener("click", () => setView(state.view === "character" ? "skeleton" : "character"));
  }
  if (config.rig_poses) {
    $("skeleton-label").hidden = false;
    $("skeleton").addEventListener("change", (e) => {
      state.skeleton = e.target.value;
      setAlternative(state.alternative).catch(fail);
    });
  }
  window.addEventListener("keydown", (e) => {
    if (e.code === "Space" && e.target === document.body) {
      e.preventDefault();
      play.click();
    }
  });
}

function setView(view) {
  state.view = view;
  return setAlternative(state.alternative).catch(fail);
}

async function main() {
  $("title").textContent = config.title || "";
  if (config.rig_models && config.rig_poses) {
    state.skeleton = "rig"; // a character of one's own is what one wants to see first
    $("skeleton").value = "rig";
  }
  wireControls();
  requestAnimationFrame(frame);
  state.timeline = await getJson(config.timeline);
  const tl = state.timeline;
  const select = $("alternative");
  tl.alternatives.forEach((alt, k) => {
    const cost = typeof alt.cost === "number" ? ` (cost ${alt.cost.toFixed(2)})` : "";
    select.appendChild(new Option(`${k}${cost}`, String(k)));
  });
  drawStage(((tl.provenance || {}).spec || {}).stage);
  buildTimeline();
  audio.src = config.audio;
  await setAlternative(0);
  $("play").disabled = false;
  state.ready = true;
  const song = tl.song || {};
  setStatus(`${tl.bars.length} bars · ${Math.round(song.tempo_bpm || 0)} bpm · ${tl.alternatives.length} alternatives`);
}

audio.addEventListener("error", () => fail(new Error(`the song could not be played (${audio.error ? audio.error.message || audio.error.code : "?"})`)));

// The test hook (see tests/services/test_preview_browser.py): read-only views of the state and
// the actions a user has, in code.
window.__preview = {
  get ready() {
    return state.ready;
  },
  get error() {
    return state.error;
  },
  get time() {
    return audio.currentTime;
  },
  get alternative() {
    return state.alternative;
  },
  get bar() {
    return state.bar;
  },
  get alternatives() {
    return state.timeline ? state.timeline.alternatives.length : 0;
  },
  get view() {
    return state.view;
  },
  // the skinned character in view: its mesh's world bounding box, or null (skeleton view)
  character: () => {
    if (!state.model) return null;
    const box = new THREE.Box3();
    state.model.root.updateMatrixWorld(true);
    state.model.root.traverse((o) => {
      if (o.isSkinnedMesh) {
        o.computeBoundingBox();
        box.union(o.boundingBox.clone().applyMatrix4(o.matrixWorld));
      }
    });
    return { min: box.min.toArray(), max: box.max.toArray() };
  },
  setView,
  pose: () => (state.pose ? Array.from(state.pose) : null),
  // a couple: the follow's pose last drawn (null for a solo dance), and how many skeletons the
  // scene holds (1, or 2 for a couple)
  followPose: () => (state.followTrack && state.followPose ? Array.from(state.followPose) : null),
  get skeletons() {
    return [lead, follow].filter((f) => f.joints && f.joints.parent === scene).length;
  },
  poseAt: (t) => (state.track ? Array.from(samplePose(state.track, t)) : null),
  seek,
  play: () => audio.play(),
  pause: () => audio.pause(),
  setAlternative,
  selectBar,
};

main().catch(fail);
