// 3D occupancy viewer of t3fast (written into each page by t3fast/viz/viewer.py).
//
// The page defines `THREE` (three.js, inlined) before this code and holds the data as JSON
// in <script id="t3-data">: label volumes packed by t3fast/viz/voxel_pack.py, the views
// (which volume each view shows at each time step), the time steps, the trajectories.
// Coordinates are the ego frame of t3fast: x forward, y left, z up, metres; the camera
// keeps z up.
//
// For tests and headless screenshots: the URL hash sets the state (#frame=7&mask=dark),
// <pre id="t3-checksums"> receives the per-frame voxel count of every class id once the
// data is decoded, and body[data-ready="1"] is set after the first frame is drawn (with
// data-ready-ms, the milliseconds since the page started), body[data-error] if anything fails.

const CUBE_SHADES = [0.8, 0.8, 0.62, 0.62, 1.0, 0.45]; // BoxGeometry faces +x -x +y -y +z -z; the top keeps the exact palette colour
const UNSEEN_DARKEN = 0.12; // linear-light factor (about 0.4 in sRGB) for voxels outside the camera mask
const BACKGROUND = 0x24262b;
const TRAJECTORY_WIDTH = 0.35; // metres
const MASK_MODES = ["show", "dark", "hide"];

// ---------------------------------------------------------------- decoding

function base64Bytes(text) {
  const bin = atob(text);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

async function inflate(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// Decode a voxel pack into {t, x, y, z, kind, data}: data holds the t volumes one after the
// other, each flattened z slowest, then x, then y (index ((z * X) + x) * Y + y).
async function unpack(text) {
  const raw = await inflate(base64Bytes(text));
  const view = new DataView(raw.buffer);
  const magic = String.fromCharCode(...raw.subarray(0, 4));
  if (magic !== "T3VX" || raw[4] !== 1) throw new Error(`voxel pack: unknown header ${magic} v${raw[4]}`);
  const kind = raw[5];
  const t = view.getUint32(6, true);
  const [x, y, z] = [view.getUint16(10, true), view.getUint16(12, true), view.getUint16(14, true)];
  const n = x * y * z;
  let offset = 16;
  let total = 0;
  for (let f = 0; f < t; f++) total += view.getUint32(offset + 4 * f, true);
  offset += 4 * t;
  const values = raw.subarray(offset, offset + total);
  let cursor = offset + total; // the run lengths, LEB128 varints
  const data = new Uint8Array(t * n);
  let pos = 0;
  for (let r = 0; r < total; r++) {
    let length = 0;
    let shift = 0;
    let byte;
    do {
      byte = raw[cursor++];
      length += (byte & 0x7f) * 2 ** shift;
      shift += 7;
    } while (byte & 0x80);
    data.fill(values[r], pos, pos + length);
    pos += length;
  }
  if (pos !== t * n) throw new Error(`voxel pack: runs cover ${pos} voxels, expected ${t * n}`);
  return { t, x, y, z, kind, data };
}

// Voxel count of each id in `ids` per volume: [t][ids.length].
function classCounts(pack, ids) {
  const n = pack.x * pack.y * pack.z;
  const out = [];
  for (let f = 0; f < pack.t; f++) {
    const hist = new Float64Array(256);
    const vol = pack.data.subarray(f * n, (f + 1) * n);
    for (let i = 0; i < n; i++) hist[vol[i]]++;
    out.push(ids.map((id) => hist[id]));
  }
  return out;
}

// ---------------------------------------------------------------- voxels to instances

// Indices of the occupied voxels of one volume that can be seen: not free, not ignore, and
// not enclosed on all six sides by occupied voxels (the grid floor counts as occupied, the
// grid sides as empty). With `seen` (mask volume), unseen voxels count as empty.
function surfaceVoxels(vol, seen, dims, free, ignore) {
  const [X, Y, Z] = dims;
  const plane = X * Y;
  const occupied = new Uint8Array(vol.length);
  for (let i = 0; i < vol.length; i++) {
    const v = vol[i];
    occupied[i] = v !== free && v !== ignore && (!seen || seen[i]) ? 1 : 0;
  }
  const out = [];
  for (let z = 0; z < Z; z++) {
    for (let x = 0; x < X; x++) {
      const row = z * plane + x * Y;
      for (let y = 0; y < Y; y++) {
        const i = row + y;
        if (!occupied[i]) continue;
        const enclosed =
          y > 0 && y < Y - 1 && x > 0 && x < X - 1 && z < Z - 1 &&
          occupied[i - 1] && occupied[i + 1] && occupied[i - Y] && occupied[i + Y] &&
          occupied[i + plane] && (z === 0 || occupied[i - plane]);
        if (!enclosed) out.push(i);
      }
    }
  }
  return Int32Array.from(out);
}

function cubeGeometry(size) {
  const geometry = new THREE.BoxGeometry(size, size, size);
  const colours = new Float32Array(geometry.attributes.position.count * 3);
  for (const [face, shade] of CUBE_SHADES.entries()) colours.fill(shade, face * 12, face * 12 + 12);
  geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3));
  return geometry;
}

// One InstancedMesh per view, refilled for each frame (translation-only matrices).
function voxelMesh(capacity, size) {
  const material = new THREE.MeshBasicMaterial({ vertexColors: true });
  const mesh = new THREE.InstancedMesh(cubeGeometry(size), material, Math.max(capacity, 1));
  const m = mesh.instanceMatrix.array;
  for (let k = 0; k < mesh.count; k++) m[16 * k] = m[16 * k + 5] = m[16 * k + 10] = m[16 * k + 15] = 1;
  mesh.instanceColor = new THREE.InstancedBufferAttribute(new Float32Array(3 * mesh.count), 3);
  mesh.frustumCulled = false; // the bounding sphere would go stale as instances change
  return mesh;
}

// ---------------------------------------------------------------- scene furniture

function linearColour(rgb, scale = 1) {
  const c = new THREE.Color().setRGB(rgb[0] / 255, rgb[1] / 255, rgb[2] / 255, THREE.SRGBColorSpace);
  return [c.r * scale, c.g * scale, c.b * scale];
}

// A flat ribbon through `points` [[x, y]...] starting at the ego, with a square at each waypoint.
function trajectoryObject(points, rgb, z) {
  const group = new THREE.Group();
  const material = new THREE.MeshBasicMaterial({ color: new THREE.Color().setRGB(...linearColour(rgb)) });
  const path = [[0, 0], ...points];
  for (let k = 1; k < path.length; k++) {
    const [x0, y0] = path[k - 1];
    const [x1, y1] = path[k];
    const length = Math.hypot(x1 - x0, y1 - y0);
    if (length > 1e-6) {
      const segment = new THREE.Mesh(new THREE.BoxGeometry(length, TRAJECTORY_WIDTH, 0.05), material);
      segment.position.set((x0 + x1) / 2, (y0 + y1) / 2, z);
      segment.rotation.z = Math.atan2(y1 - y0, x1 - x0);
      group.add(segment);
    }
    const dot = new THREE.Mesh(new THREE.BoxGeometry(0.8, 0.8, 0.08), material);
    dot.position.set(x1, y1, z);
    group.add(dot);
  }
  return group;
}

function egoObject(ego, groundTop) {
  const geometry = new THREE.BoxGeometry(ego.length, ego.width, ego.height);
  const box = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial({ color: new THREE.Color().setRGB(...linearColour(ego.color)) }));
  box.position.set(0, 0, groundTop + ego.height / 2);
  const edges = new THREE.LineSegments(new THREE.EdgesGeometry(geometry), new THREE.LineBasicMaterial({ color: 0x000000 }));
  box.add(edges);
  return box;
}

// ---------------------------------------------------------------- camera

// Orbit camera around a target, z up: drag rotates, right-drag or shift-drag pans, the
// wheel zooms, double-click resets. One instance drives every view, so they stay linked.
class Orbit {
  constructor(element, camera, home, onChange) {
    Object.assign(this, { element, camera, home, onChange });
    this.reset();
    let last = null;
    element.addEventListener("contextmenu", (e) => e.preventDefault());
    element.addEventListener("pointerdown", (e) => {
      last = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
      element.setPointerCapture(e.pointerId);
    });
    element.addEventListener("pointerup", () => (last = null));
    element.addEventListener("pointermove", (e) => {
      if (!last) return;
      const dx = e.clientX - last.x;
      const dy = e.clientY - last.y;
      last.x = e.clientX;
      last.y = e.clientY;
      if (last.pan) this.pan(dx, dy);
      else {
        this.azimuth -= dx * 0.008;
        this.elevation = Math.min(1.55, Math.max(0.05, this.elevation + dy * 0.008));
      }
      this.update();
    });
    element.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.distance = Math.min(400, Math.max(3, this.distance * Math.exp(e.deltaY * 0.001)));
      this.update();
    }, { passive: false });
    element.addEventListener("dblclick", () => this.reset());
  }

  reset() {
    this.target = new THREE.Vector3(...this.home.target);
    Object.assign(this, { azimuth: this.home.azimuth, elevation: this.home.elevation, distance: this.home.distance });
    this.update();
  }

  pan(dx, dy) {
    const scale = this.distance / 700;
    const right = new THREE.Vector3(-Math.sin(this.azimuth), Math.cos(this.azimuth), 0);
    const forward = new THREE.Vector3(Math.cos(this.azimuth), Math.sin(this.azimuth), 0);
    this.target.addScaledVector(right, -dx * scale).addScaledVector(forward, dy * scale);
  }

  update() {
    const c = Math.cos(this.elevation);
    const offset = new THREE.Vector3(
      c * Math.cos(this.azimuth + Math.PI), c * Math.sin(this.azimuth + Math.PI), Math.sin(this.elevation));
    this.camera.position.copy(this.target).addScaledVector(offset, this.distance);
    this.camera.lookAt(this.target);
    this.onChange?.();
  }
}

// ---------------------------------------------------------------- page

function element(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else if (k === "style") node.style.cssText = v;
    else node.setAttribute(k, v);
  }
  node.append(...children);
  return node;
}

function readHash() {
  const params = new URLSearchParams(location.hash.slice(1));
  return { frame: params.get("frame"), mask: params.get("mask") };
}

function buildLegend(data, present) {
  const items = data.classNames.map((name, id) =>
    id === data.free ? null : element("li", { class: present.has(id) ? "" : "absent", title: `class ${id}` },
      element("span", { class: "swatch", style: `background: rgb(${data.palette[id].join(",")})` }), name));
  const extras = [...data.trajectories.map((t) => ({ ...t, kind: "swatch line" })),
    { name: "ego", color: data.ego.color, kind: "swatch" }].map((t) =>
    element("li", {}, element("span", { class: t.kind, style: `background: rgb(${t.color.join(",")})` }), t.name));
  return element("ul", { id: "t3-legend" }, ...items.filter(Boolean), ...extras);
}

async function main() {
  const data = JSON.parse(document.getElementById("t3-data").textContent);
  const names = Object.keys(data.sequences);
  const packs = Object.fromEntries(await Promise.all(names.map(async (k) => [k, await unpack(data.sequences[k])])));
  const masks = data.masks ? await unpack(data.masks) : null;

  // the checksums a test compares with the Python labels
  const ids = [...Array(data.free + 1).keys(), data.ignore];
  const counts = Object.fromEntries(names.map((k) => [k, classCounts(packs[k], ids)]));
  const maskCounts = masks ? classCounts(masks, [1]).map((c) => c[0]) : null;
  document.getElementById("t3-checksums").textContent = JSON.stringify({ classes: ids, sequences: counts, masks: maskCounts });
  const present = new Set();
  for (const seq of Object.values(counts)) for (const frame of seq) frame.forEach((c, j) => c && present.add(ids[j]));

  // page layout
  const app = document.getElementById("t3-app");
  const slider = element("input", { type: "range", min: 0, max: data.steps.length - 1, value: 0, id: "t3-frame" });
  const play = element("button", { id: "t3-play", type: "button" }, "play");
  const time = element("span", { id: "t3-time" });
  const maskSelect = element("select", { id: "t3-mask", title: "voxels outside the camera visibility mask" },
    ...MASK_MODES.map((m) => element("option", { value: m }, { show: "unseen: shown", dark: "unseen: darkened", hide: "unseen: hidden" }[m])));
  const reset = element("button", { type: "button", title: "or double-click the view" }, "reset view");
  const controls = element("div", { id: "t3-controls" }, play, slider, time, ...(masks ? [maskSelect] : []), reset);
  const share = 100 / data.views.length;
  const labels = data.views.map((v, k) =>
    element("div", { class: "view-label", style: `left: ${k * share}%; width: ${share}%` }, v.name));
  const stage = element("div", { id: "t3-stage" }, ...labels);
  app.append(element("header", {}, element("h1", {}, data.title || "occupancy"), controls),
    element("main", {}, stage, buildLegend(data, present)));

  // three.js: one canvas, one camera, one viewport per view
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setClearColor(BACKGROUND);
  stage.prepend(renderer.domElement);
  const camera = new THREE.PerspectiveCamera(40, 1, 0.5, 1000);
  camera.up.set(0, 0, 1);

  const [X, Y, Z] = data.grid.shape;
  const vs = data.grid.voxel;
  const lower = data.grid.lower;
  const groundTop = lower[2] + vs; // top of the lowest voxel layer
  const surfaces = new Map();
  const surfaceOf = (seq, index, step, hide) => {
    const key = `${seq}:${index}:${hide ? step : ""}`;
    if (!surfaces.has(key)) {
      const n = X * Y * Z;
      const vol = packs[seq].data.subarray(index * n, (index + 1) * n);
      const seen = hide ? masks.data.subarray(step * n, (step + 1) * n) : null;
      surfaces.set(key, surfaceVoxels(vol, seen, [X, Y, Z], data.free, data.ignore));
    }
    return surfaces.get(key);
  };
  // instances to allocate: the most occupied voxels of any frame (a bound on its surface voxels)
  const occupiedIds = ids.map((id) => id !== data.free && id !== data.ignore);
  const occupiedCount = (frame) => frame.reduce((sum, n, j) => sum + (occupiedIds[j] ? n : 0), 0);
  const capacity = Math.max(...Object.values(counts).flat().map(occupiedCount));

  const colours = data.palette.map((rgb) => linearColour(rgb));
  const darkColours = data.palette.map((rgb) => linearColour(rgb, UNSEEN_DARKEN));
  const views = data.views.map((v) => {
    const scene = new THREE.Scene();
    const mesh = voxelMesh(capacity, vs);
    scene.add(mesh, egoObject(data.ego, groundTop));
    data.trajectories.forEach((t, k) => scene.add(trajectoryObject(t.points, t.color, groundTop + 0.03 + 0.02 * k)));
    return { ...v, scene, mesh };
  });

  const state = { step: 0, mask: "show", timer: null };
  const render = () => {
    const width = stage.clientWidth;
    const height = stage.clientHeight;
    const w = width / views.length;
    camera.aspect = w / height;
    camera.updateProjectionMatrix();
    renderer.setScissorTest(true);
    views.forEach((v, k) => {
      renderer.setViewport(k * w, 0, w, height);
      renderer.setScissor(k * w, 0, w, height);
      renderer.render(v.scene, camera);
    });
  };
  const orbit = new Orbit(renderer.domElement, camera, data.camera, render);
  reset.addEventListener("click", () => orbit.reset());

  const fill = (v) => {
    const [seq, index] = v.frames[state.step];
    const n = X * Y * Z;
    const vol = packs[seq].data.subarray(index * n, (index + 1) * n);
    const seen = masks && state.mask !== "show" ? masks.data.subarray(state.step * n, (state.step + 1) * n) : null;
    const voxels = surfaceOf(seq, index, state.step, seen && state.mask === "hide");
    const m = v.mesh.instanceMatrix.array;
    const c = v.mesh.instanceColor.array;
    voxels.forEach((i, k) => {
      const y = i % Y;
      const x = Math.floor(i / Y) % X;
      const z = Math.floor(i / (X * Y));
      m[16 * k + 12] = lower[0] + vs * (x + 0.5);
      m[16 * k + 13] = lower[1] + vs * (y + 0.5);
      m[16 * k + 14] = lower[2] + vs * (z + 0.5);
      const rgb = (seen && !seen[i] ? darkColours : colours)[vol[i]];
      c[3 * k] = rgb[0];
      c[3 * k + 1] = rgb[1];
      c[3 * k + 2] = rgb[2];
    });
    v.mesh.count = voxels.length;
    v.mesh.instanceMatrix.needsUpdate = true;
    v.mesh.instanceColor.needsUpdate = true;
  };

  const show = (step, mask = state.mask) => {
    state.step = Math.min(data.steps.length - 1, Math.max(0, step | 0));
    state.mask = masks && MASK_MODES.includes(mask) ? mask : "show";
    slider.value = state.step;
    maskSelect.value = state.mask;
    time.textContent = data.steps[state.step];
    views.forEach((v, k) => {
      fill(v);
      labels[k].textContent = `${v.name} · ${data.steps[state.step]}`;
    });
    history.replaceState(null, "", `#frame=${state.step}${state.mask !== "show" ? `&mask=${state.mask}` : ""}`);
    render();
  };
  const fromHash = () => {
    const h = readHash();
    show(h.frame === null ? state.step : Number(h.frame), h.mask ?? state.mask);
  };

  slider.addEventListener("input", () => show(Number(slider.value)));
  maskSelect.addEventListener("change", () => show(state.step, maskSelect.value));
  play.addEventListener("click", () => {
    if (state.timer) {
      clearInterval(state.timer);
      state.timer = null;
      play.textContent = "play";
    } else {
      state.timer = setInterval(() => show((state.step + 1) % data.steps.length), 1000 * data.frameDt);
      play.textContent = "pause";
    }
  });
  window.addEventListener("hashchange", fromHash);
  window.addEventListener("resize", () => {
    renderer.setSize(stage.clientWidth, stage.clientHeight);
    render();
  });
  renderer.setSize(stage.clientWidth, stage.clientHeight);
  fromHash();
  document.body.dataset.readyMs = Math.round(performance.now());
  document.body.dataset.ready = "1";
}

function fail(error) {
  const message = String(error?.stack || error?.message || error);
  document.body.dataset.error = message;
  document.getElementById("t3-error").textContent = `The viewer failed: ${message}`;
  document.getElementById("t3-error").hidden = false;
}

window.addEventListener("error", (e) => fail(e.error || e.message));
main().catch((e) => {
  console.error(e);
  fail(e);
});
