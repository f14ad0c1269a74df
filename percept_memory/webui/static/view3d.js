// The 3D view of a scene or a map (webui/scene3d.py): draws what the page's JSON data block
// describes with three.js, z up as in the map frame. Boxes are clusters or regions; a scene's
// camera is a frustum; a map's objects are dots (blue: seen there, grey: hidden). The points
// come as binary from the URL the data names. The canvas is drawn on demand, when something
// changes, and says how often in data-drawn (and how many points in data-points).
import * as THREE from "./three/three.module.js";
import { OrbitControls } from "./three/OrbitControls.js";

const COLOURS = { box: 0xff3b30, region: 0x8a939e, frustum: 0x0a5cc2, present: 0x0a5cc2,
                  hidden: 0x8a939e, label: "#1d232b", boxLabel: "#c0261d", regionLabel: "#5b6470" };
const canvas = document.querySelector("canvas.view3d");
const data = JSON.parse(document.getElementById("view3d-data").textContent);

const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
const world = new THREE.Scene();
world.background = new THREE.Color(0xf4f6f8);
const camera = new THREE.PerspectiveCamera(50, 16 / 9, 0.01, 500);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, canvas);
controls.addEventListener("change", draw);

function draw() {
  renderer.render(world, camera);
  canvas.dataset.drawn = String(Number(canvas.dataset.drawn || 0) + 1);
}

function resize() {
  const width = canvas.clientWidth, height = canvas.clientHeight;
  renderer.setSize(width, height, false);
  camera.aspect = width / height;
  camera.updateProjectionMatrix();
  draw();
}

function label(text, at, colour = COLOURS.label) {
  // Text as a sprite of constant size on screen: 13 px, drawn at twice that for sharpness.
  const sharpness = 2, font = 13 * sharpness;
  const paper = document.createElement("canvas");
  const pen = paper.getContext("2d");
  pen.font = `${font}px system-ui, sans-serif`;
  paper.width = Math.ceil(pen.measureText(text).width) + 8;
  paper.height = font + 8;
  pen.font = `${font}px system-ui, sans-serif`;  // (sizing the paper reset the pen)
  pen.fillStyle = "rgba(255, 255, 255, 0.8)";
  pen.fillRect(0, 0, paper.width, paper.height);
  pen.fillStyle = colour;
  pen.fillText(text, 4, font);
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({
    map: new THREE.CanvasTexture(paper), depthTest: false, sizeAttenuation: false }));
  const focal = 1 / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  sprite.scale.set(paper.width, paper.height, 1)
    .multiplyScalar(2 / (sharpness * focal * canvas.clientHeight));
  sprite.center.set(0, 0);
  sprite.position.set(...at);
  sprite.renderOrder = 1;
  return sprite;
}

function box({ low, high, label: text, region }) {
  const group = new THREE.Group();
  const bounds = new THREE.Box3(new THREE.Vector3(...low), new THREE.Vector3(...high));
  group.add(new THREE.Box3Helper(bounds, region ? COLOURS.region : COLOURS.box));
  if (region) {  // a translucent floor under the objects of the region
    const size = bounds.getSize(new THREE.Vector3());
    const floor = new THREE.Mesh(new THREE.PlaneGeometry(size.x, size.y),
      new THREE.MeshBasicMaterial({ color: 0xffffff, transparent: true, opacity: 0.6,
                                    side: THREE.DoubleSide }));
    floor.position.set((low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]);
    group.add(floor);
  }
  const colour = region ? COLOURS.regionLabel : COLOURS.boxLabel;
  group.add(label(text, [low[0], low[1], high[2]], colour));
  return group;
}

function frustum([apex, ...corners]) {
  // From the camera to each far corner, and round the far end.
  const ends = corners.flatMap((corner, i) => [apex, corner, corner, corners[(i + 1) % 4]]);
  const geometry = new THREE.BufferGeometry()
    .setFromPoints(ends.map((p) => new THREE.Vector3(...p)));
  return new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color: COLOURS.frustum }));
}

function dot({ position, label: text, state }) {
  const group = new THREE.Group();
  const hidden = state !== "present";
  const ball = new THREE.Mesh(new THREE.SphereGeometry(0.05, 16, 12),
    new THREE.MeshBasicMaterial({ color: hidden ? COLOURS.hidden : COLOURS.present,
                                  transparent: hidden, opacity: hidden ? 0.5 : 1 }));
  ball.position.set(...position);
  group.add(ball, label(text, [position[0] + 0.06, position[1], position[2] + 0.06]));
  return group;
}

async function cloud(url) {
  const answer = await fetch(url);
  if (!answer.ok) throw new Error(`${url}: HTTP ${answer.status}`);
  const bytes = await answer.arrayBuffer();
  const count = bytes.byteLength / 15;  // 3 float32 and 3 uint8 per point
  const geometry = new THREE.BufferGeometry();
  const positions = new Float32Array(bytes, 0, count * 3);
  const colours = new Uint8Array(bytes, count * 12);  // 0-255, normalised to 0-1 below
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3, true));
  canvas.dataset.points = String(count);
  return new THREE.Points(geometry, new THREE.PointsMaterial({
    size: 2, sizeAttenuation: false, vertexColors: true }));
}

function look() {
  // A scene from just behind its camera towards its clusters, as the robot saw them; a map
  // from the south, above.
  const bounds = new THREE.Box3();
  for (const b of data.boxes || []) bounds.expandByPoint(new THREE.Vector3(...b.low))
                                          .expandByPoint(new THREE.Vector3(...b.high));
  if (bounds.isEmpty()) bounds.setFromObject(world);
  if (bounds.isEmpty()) bounds.set(new THREE.Vector3(-1, -1, 0), new THREE.Vector3(1, 1, 1));
  const centre = bounds.getCenter(new THREE.Vector3());
  if (data.frustum) {
    const apex = new THREE.Vector3(...data.frustum[0]);
    camera.position.copy(apex).add(apex.clone().sub(centre).multiplyScalar(0.25));
  } else {
    const radius = Math.max(bounds.getSize(new THREE.Vector3()).length() / 2, 0.3);
    const away = 0.8 * radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2));
    camera.position.copy(centre).add(new THREE.Vector3(0, -1, 1.2).setLength(away));
  }
  controls.target.copy(centre);
  controls.update();
}

for (const b of data.boxes || []) world.add(box(b));
for (const o of data.objects || []) world.add(dot(o));
if (data.frustum) world.add(frustum(data.frustum));
look();
world.add(new THREE.AxesHelper(0.25));  // the frame's origin (x red, y green, z blue)
new ResizeObserver(resize).observe(canvas);
if (data.cloud) {
  world.add(await cloud(data.cloud));
  draw();
}
