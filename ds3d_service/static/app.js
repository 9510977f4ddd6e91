// The ds3d page: a photo in (file, drop, paste or webcam), POST /v1/pose, the answer drawn: the
// 2D skeleton over the photo and a 3D view to turn and zoom. Plain JavaScript and canvas 2D, no
// build step and nothing loaded from elsewhere (the page's Content-Security-Policy forbids it).

// ---------------------------------------------------------------------------------------------
// The skeleton: the limbs drawn between the joints of every answer's joints_2d and joints_3d
// (LSP order, "right" being the person's right), each joint's colour and the joint sets, as the
// service gives them (GET /v1/skeleton, made from ds3d/skeleton.py and the colours of
// ds3d/viz/overlay.py, so that the page and the saved pictures read the same).

const SKELETON = {
  limbs: [], // [child, parent] joint indices
  colours: [], // per joint: the CSS colour of the limb that ends at it
  sets: {}, // joint set name -> {description, joints}
  hips: [], // the right and left hips: the 3D view stands each person on their midpoint
};

async function loadSkeleton() {
  // relative: the page and the API share their origin and any path prefix
  const response = await fetch("v1/skeleton");
  if (!response.ok) throw new Error(`HTTP ${response.status}`);
  const body = await response.json();
  const css = ([r, g, b]) => `rgb(${r}, ${g}, ${b})`;
  SKELETON.limbs = body.limbs;
  SKELETON.colours = body.sides.map((side) => css(body.colours[side]));
  SKELETON.sets = body.joint_sets;
  SKELETON.hips = ["right_hip", "left_hip"].map((name) => body.joint_names.indexOf(name));
  // the legend's swatches (style.css: var(--right), var(--left), var(--centre))
  for (const [side, rgb] of Object.entries(body.colours)) {
    document.documentElement.style.setProperty(`--${side}`, css(rgb));
  }
}

// Fetched once, at once; an answer is drawn only after it. null once loaded, else why not.
const skeletonLoaded = loadSkeleton().then(
  () => null,
  (err) => err.message,
);

// ---------------------------------------------------------------------------------------------
// State.

const $ = (id) => document.getElementById(id);

const KEY_STORAGE = "ds3d.apiKey"; // sessionStorage only: the key leaves with the tab
const PHOTO_SIDE = 1200; // px: the 2D canvas's longer side, whatever the photo's size
const BACKGROUND_3D = "#f7f7f5";
// degrees, degrees, mm; distance null: as near as shows the whole scene (fitDistance)
const DEFAULT_VIEW = { yaw: 30, pitch: 15, distance: null };

const state = {
  file: null, // the photo (File or Blob) last chosen: what is sent
  fileName: "",
  picture: null, // its decoded ImageBitmap, or null where the browser cannot decode it
  box: null, // [x0, y0, x1, y1] photo px: the user's box around the person, or null
  answer: null, // the last successful JSON answer
  people: [], // its people: [{joints_2d, joints_3d, confidence, box, score, ...}]
  scene: null, // the 3D skeletons placed for the 3D view
  fit: 4000, // mm: the eye's distance that shows the whole scene at the default angles
  request: null, // AbortController of the request in flight
  camera: null, // the webcam's MediaStream while it is open
};
const view = { ...DEFAULT_VIEW };

// ---------------------------------------------------------------------------------------------
// Input: a file, a drop, a paste or a webcam frame; every one ends in setPhoto.

async function setPhoto(file, name) {
  state.file = file;
  state.fileName = name || file.name || "photo";
  setBox(null);
  clearAnswer();
  state.picture?.close(); // a photo's pixels can be large: let them go now
  state.picture = null;
  // The photo is shown while the service works. A file the browser cannot decode is still
  // sent: the service says what is wrong with it, in its own words.
  state.picture = await createImageBitmap(file).catch(() => null);
  $("run").disabled = false;
  draw2d();
  await estimate();
}

function wireInputs() {
  $("file").addEventListener("change", (event) => {
    const [file] = event.target.files;
    if (file) setPhoto(file);
    event.target.value = ""; // choosing the same file again is a new choice
  });

  // Drops anywhere on the page: a photo that misses the drop zone must not replace the page.
  const drop = $("drop");
  document.addEventListener("dragover", (event) => {
    event.preventDefault();
    drop.classList.add("dragging");
  });
  document.addEventListener("dragleave", (event) => {
    if (!event.relatedTarget) drop.classList.remove("dragging");
  });
  document.addEventListener("drop", (event) => {
    event.preventDefault();
    drop.classList.remove("dragging");
    const [file] = event.dataTransfer?.files || [];
    if (file) setPhoto(file);
  });

  // A pasted image; pasted text goes to the text field as usual.
  document.addEventListener("paste", (event) => {
    const files = [...(event.clipboardData?.files || [])];
    const image = files.find((f) => f.type.startsWith("image/"));
    if (!image) return;
    event.preventDefault();
    setPhoto(image, image.name && image.name !== "image.png" ? image.name : "pasted image");
  });

  $("run").addEventListener("click", () => estimate());
  $("all-people").addEventListener("change", () => state.file && estimate());
  $("bbox").addEventListener("change", boxTyped);
  $("bbox-clear").addEventListener("click", () => {
    setBox(null);
    draw2d();
    if (state.file) estimate();
  });
  wireKey();
  wireCamera();
}

function wireKey() {
  const field = $("api-key");
  try {
    field.value = sessionStorage.getItem(KEY_STORAGE) || "";
  } catch {
    // storage refused (a privacy mode): the key lasts as long as the field
  }
  if (field.value) $("key-details").open = true;
  field.addEventListener("input", () => {
    try {
      if (field.value) sessionStorage.setItem(KEY_STORAGE, field.value);
      else sessionStorage.removeItem(KEY_STORAGE);
    } catch {
      // as above
    }
  });
}

// The webcam button appears only where the browser has a camera API (not over plain http
// from another host: browsers keep cameras to secure origins).
function wireCamera() {
  if (!navigator.mediaDevices?.getUserMedia) return;
  $("camera-open").hidden = false;
  $("camera-open").addEventListener("click", openCamera);
  $("camera-close").addEventListener("click", closeCamera);
  $("camera-snap").addEventListener("click", snapCamera);
}

async function openCamera() {
  try {
    // the back camera where there are two: the photo is usually of someone else
    state.camera = await navigator.mediaDevices.getUserMedia({
      video: { facingMode: { ideal: "environment" } },
      audio: false,
    });
  } catch (err) {
    showProblem(`The camera could not be opened: ${err.message || err.name}.`);
    return;
  }
  const video = $("video");
  video.srcObject = state.camera;
  $("camera").hidden = false;
  await video.play().catch(() => {});
  $("camera-snap").focus();
}

function closeCamera() {
  state.camera?.getTracks().forEach((track) => track.stop());
  state.camera = null;
  $("video").srcObject = null;
  $("camera").hidden = true;
  $("camera-open").focus();
}

function snapCamera() {
  const video = $("video");
  if (!video.videoWidth) return; // no frame yet
  const frame = document.createElement("canvas");
  frame.width = video.videoWidth;
  frame.height = video.videoHeight;
  frame.getContext("2d").drawImage(video, 0, 0);
  frame.toBlob(
    (blob) => {
      closeCamera();
      if (blob) setPhoto(new File([blob], "camera.jpg", { type: "image/jpeg" }));
    },
    "image/jpeg",
    0.92,
  );
}

// ---------------------------------------------------------------------------------------------
// The box around the person: dragged on the photo, or typed.

function setBox(box) {
  state.box = box;
  $("bbox").value = box ? JSON.stringify(box) : "";
}

// "[10, 20, 200, 400]" or "10 20 200 400" -> numbers; null when it is not four numbers (the
// text is then sent as typed, for the service to say what is wrong).
function parseBox(text) {
  const numbers = text.replace(/[[\]]/g, " ").split(/[\s,]+/).filter(Boolean).map(Number);
  return numbers.length === 4 && numbers.every(Number.isFinite) ? numbers : null;
}

function boxTyped() {
  const text = $("bbox").value.trim();
  state.box = text ? parseBox(text) : null;
  if (state.box) $("bbox").value = JSON.stringify(state.box);
  draw2d();
  if (state.file) estimate();
}

// Photo px under a pointer event on the 2D canvas: the canvas is scaled by CSS, and letterboxed
// (object-fit: contain) where a tall photo meets the height cap.
function photoPoint(event) {
  const canvas = $("view2d");
  const rect = canvas.getBoundingClientRect();
  const fit = Math.min(canvas.clientWidth / canvas.width, canvas.clientHeight / canvas.height);
  const left = rect.left + canvas.clientLeft + (canvas.clientWidth - canvas.width * fit) / 2;
  const top = rect.top + canvas.clientTop + (canvas.clientHeight - canvas.height * fit) / 2;
  const [width, height] = photoSize();
  const x = ((event.clientX - left) / (canvas.width * fit)) * width;
  const y = ((event.clientY - top) / (canvas.height * fit)) * height;
  return [Math.min(Math.max(x, 0), width), Math.min(Math.max(y, 0), height)];
}

function wireBoxDrag() {
  const canvas = $("view2d");
  let start = null;
  canvas.addEventListener("pointerdown", (event) => {
    if (!state.picture || event.button !== 0) return;
    capture(canvas, event);
    start = photoPoint(event);
  });
  canvas.addEventListener("pointermove", (event) => {
    if (!start) return;
    state.box = orderedBox(start, photoPoint(event));
    draw2d();
  });
  const finish = (event) => {
    if (!start) return;
    const box = orderedBox(start, photoPoint(event));
    start = null;
    // A click, or a box too small to hold anyone, is no box.
    const [width, height] = photoSize();
    const minimum = 0.03 * Math.max(width, height);
    if (event.type === "pointercancel" || box[2] - box[0] < minimum || box[3] - box[1] < minimum) {
      state.box = parseBox($("bbox").value);
      draw2d();
      return;
    }
    setBox(box);
    draw2d();
    estimate();
  };
  canvas.addEventListener("pointerup", finish);
  canvas.addEventListener("pointercancel", finish);
}

// Keep receiving a drag's moves when it leaves the canvas. (A pointer the browser does not
// know, as in a synthetic event, cannot be captured: the drag then works inside the canvas.)
function capture(canvas, event) {
  try {
    canvas.setPointerCapture(event.pointerId);
  } catch {
    // see above
  }
}

// The API's box of photo px corners [x0, y0, x1, y1]: its centre and sides as fractions of the
// photo's width and height.
function fractionBox([x0, y0, x1, y1]) {
  const { width, height } = state.picture;
  return {
    cx: (x0 + x1) / 2 / width,
    cy: (y0 + y1) / 2 / height,
    width: (x1 - x0) / width,
    height: (y1 - y0) / height,
  };
}

function orderedBox([ax, ay], [bx, by]) {
  return [Math.min(ax, bx), Math.min(ay, by), Math.max(ax, bx), Math.max(ay, by)].map(Math.round);
}

// ---------------------------------------------------------------------------------------------
// The request.

function buildRequest() {
  const form = new FormData();
  form.append("image", state.file, state.fileName);
  const boxText = $("bbox").value.trim();
  if (state.box && state.picture) form.append("box", JSON.stringify(fractionBox(state.box)));
  // Without the photo's size (a format this browser does not show), or as text that is not four
  // numbers, the box goes as the corner form in px, for the service to place or to refuse.
  else if (boxText) form.append("bbox", state.box ? JSON.stringify(state.box) : boxText);
  const intrinsics = $("intrinsics").value.trim();
  if (intrinsics) form.append("intrinsics", intrinsics);
  const headers = {};
  const key = $("api-key").value.trim();
  if (key) headers.Authorization = `Bearer ${key}`;
  const people = $("all-people").checked ? "all" : "best";
  // relative: the page and the API share their origin and any path prefix
  return [`v1/pose?people=${people}`, { method: "POST", body: form, headers }];
}

async function estimate() {
  if (!state.file) return;
  const noSkeleton = await skeletonLoaded;
  if (noSkeleton) {
    setStatus("No skeleton to draw with.");
    showProblem(`The service's skeleton could not be read (${noSkeleton}): reload the page.`);
    countAnswer();
    return;
  }
  state.request?.abort(); // only the latest question's answer is shown
  const controller = new AbortController();
  state.request = controller;
  const [url, options] = buildRequest();
  hideProblem();
  $("run").disabled = true;
  setStatus(`Estimating the pose in ${state.fileName} (${kilobytes(state.file.size)})…`);
  const t0 = performance.now();
  let response;
  let text;
  try {
    response = await fetch(url, { ...options, signal: controller.signal });
    text = await response.text();
  } catch (err) {
    if (controller.signal.aborted) return;
    finishRequest(controller);
    setStatus("No answer.");
    showProblem(`The service could not be reached: ${err.message}.`);
    return;
  }
  if (state.request !== controller) return;
  finishRequest(controller);
  const seconds = ((performance.now() - t0) / 1000).toFixed(2);
  if (!response.ok) {
    setStatus(`The service answered with an error (HTTP ${response.status}).`);
    showApiError(response, text);
    countAnswer();
    return;
  }
  let answer;
  try {
    answer = JSON.parse(text);
  } catch {
    setStatus("The answer could not be read.");
    showProblem("The service's answer is not JSON: is this a ds3d service?");
    countAnswer();
    return;
  }
  showAnswer(answer);
  setStatus(`Answered in ${seconds} s.`);
  countAnswer();
}

function finishRequest(controller) {
  if (state.request === controller) state.request = null;
  $("run").disabled = !state.file;
}

// Tests and tools wait on this counter: it moves once per answer, success or error.
function countAnswer() {
  const result = $("result");
  result.dataset.answers = String(Number(result.dataset.answers || 0) + 1);
}

function kilobytes(bytes) {
  return bytes < 1e6 ? `${Math.round(bytes / 1e3)} kB` : `${(bytes / 1e6).toFixed(1)} MB`;
}

// ---------------------------------------------------------------------------------------------
// Errors: the service's own message, plainly, with what the user can do about it.

function showApiError(response, text) {
  let code = `http_${response.status}`;
  let message = response.statusText || "no message";
  try {
    ({ code, message } = JSON.parse(text).error);
  } catch {
    // not the service's JSON (a proxy's page): the status line is all there is
  }
  const retry = response.headers.get("Retry-After");
  showProblem(message, `HTTP ${response.status} · ${code}`, errorHint(response.status, retry));
}

function errorHint(status, retry) {
  const wait = retry ? ` Try again in ${retry} s.` : "";
  switch (status) {
    case 401:
      $("key-details").open = true;
      $("api-key").focus();
      return "This service needs an API key: enter it under “API key” above, then estimate again.";
    case 413:
      return "The photo is too large for this service: try a smaller one.";
    case 415:
    case 422:
      return "Check the photo (JPEG, PNG, WebP…) and the optional fields.";
    case 429:
      return `Too many requests from you just now.${wait}`;
    case 503:
      return `The service is busy or not ready.${wait}`;
    case 504:
      return "The service did not answer in time: try again, or a smaller photo.";
    default:
      return wait.trim();
  }
}

function showProblem(message, meta = "", hint = "") {
  const box = $("error");
  box.replaceChildren(); // text nodes only: the message is never read as HTML
  for (const [text, cls] of [[message, "error-message"], [meta, "error-meta"], [hint, "error-hint"]]) {
    if (!text) continue;
    const line = document.createElement("p");
    line.className = cls;
    line.textContent = text;
    box.append(line);
  }
  box.hidden = false;
  showPlace(box);
}

// On a phone the answer lands below the fold: bring it into sight, without moving a page that
// already shows it.
function showPlace(node) {
  const { top, bottom } = node.getBoundingClientRect();
  if (top < 0 || bottom > window.innerHeight) {
    const still = window.matchMedia("(prefers-reduced-motion: reduce)").matches;
    node.scrollIntoView({ block: "nearest", behavior: still ? "auto" : "smooth" });
  }
}

function hideProblem() {
  $("error").hidden = true;
  $("error").replaceChildren();
}

function setStatus(text) {
  $("status").textContent = text;
}

// ---------------------------------------------------------------------------------------------
// The answer: facts, timings, the download, and both views.

function clearAnswer() {
  state.answer = null;
  state.people = [];
  state.scene = null;
  $("download").disabled = true;
  $("facts").replaceChildren();
  $("timings").hidden = true;
  draw3d();
}

function showAnswer(answer) {
  state.answer = answer;
  // people=all answers {people: [...]}, the default one person at the top level.
  state.people = Array.isArray(answer.people) ? answer.people : [answer];
  state.scene = placeScene(state.people);
  if (state.scene) state.fit = fitDistance($("view3d"), state.scene);
  $("download").disabled = false;
  showFacts(answer);
  showTimings(answer.timings_ms || {});
  draw2d();
  draw3d();
  showPlace($("view2d"));
}

function percent(p) {
  return `${Math.round(100 * p)} %`;
}

// The joint set the 3D fit trusted most (the paper's five sets).
function jointSetText(name) {
  const set = SKELETON.sets[name];
  return set ? `${name} (${set.description})` : name;
}

// The facing said only where the model is sure: on held-out LSP train images (im0701-im1000)
// whose annotation shows which way the person faces, its facing is right 95 % of the time at
// P(faces the camera) >= FACING_SURE or <= 1 - FACING_SURE (four in five of them), and not
// much better than a guess nearer 0.5 (45-70 % face the camera at 0.3-0.7). Either way the
// pose is drawn, in 2D and 3D, as facing the likelier way.
const FACING_SURE = 0.8;

function facingText(p) {
  const way = p >= 0.5 ? "the camera" : "away";
  const sure = Math.max(p, 1 - p);
  if (sure >= FACING_SURE) return `faces ${way} (${percent(sure)})`;
  return `unsure (${percent(sure)} that it faces ${way}, as drawn): left and right may be swapped`;
}

function showFacts(answer) {
  const rows = [];
  if (Array.isArray(answer.people)) {
    rows.push(["People found", String(answer.people.length)]);
    if (!answer.people.length) {
      rows.push(["", "Nobody in this photo scored high enough: try a box around the person."]);
    }
    answer.people.forEach((person, i) => {
      const what = [
        `score ${percent(person.score)}`,
        `facing: ${facingText(person.facing_camera)}`,
        `joint set ${jointSetText(person.joint_set)}`,
      ].join(", ");
      rows.push([`Person ${i + 1}`, what]);
    });
  } else {
    const found = answer.person_found
      ? `yes (score ${percent(answer.score)})`
      : "no: nobody scored high enough; this is the likeliest candidate's pose, probably not a person's";
    rows.push(["Person found", found]);
    rows.push(["Facing", facingText(answer.facing_camera)]);
    rows.push(["Joint set", jointSetText(answer.joint_set)]);
  }
  rows.push(["Photo", photoDescription()]);
  rows.push(["Model", answer.model]);
  $("facts").replaceChildren(...rows.flatMap(([term, value]) => [element("dt", term), element("dd", value)]));
}

function photoDescription() {
  const size = state.picture ? `, ${state.picture.width} × ${state.picture.height} px` : "";
  return `${state.fileName}${size}`;
}

function showTimings(timings) {
  const body = $("timings").querySelector("tbody");
  body.replaceChildren(
    ...Object.entries(timings).map(([stage, ms]) => {
      const row = element("tr");
      row.append(element("th", stage.replaceAll("_", " ")), element("td", ms.toFixed(1)));
      row.firstChild.scope = "row";
      return row;
    }),
  );
  $("timings").hidden = !body.children.length;
}

function element(tag, text = "") {
  const node = document.createElement(tag);
  node.textContent = text;
  return node;
}

function download() {
  if (!state.answer) return;
  const blob = new Blob([JSON.stringify(state.answer, null, 2)], { type: "application/json" });
  const link = document.createElement("a");
  link.href = URL.createObjectURL(blob);
  link.download = `${state.fileName.replace(/\.[^.]*$/, "") || "pose"}.ds3d.json`;
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 10_000);
}

// ---------------------------------------------------------------------------------------------
// The 2D view: the photo, the skeletons, the boxes.

// The photo's size in px: the decoded picture's, else (an image only the service could read)
// the extent of the joints.
function photoSize() {
  if (state.picture) return [state.picture.width, state.picture.height];
  const points = state.people.flatMap((p) => p.joints_2d);
  if (!points.length) return [640, 480];
  return [Math.max(...points.map((q) => q[0])) * 1.1, Math.max(...points.map((q) => q[1])) * 1.1];
}

function draw2d() {
  const canvas = $("view2d");
  const [width, height] = photoSize();
  // A fixed longer side: a small photo is drawn large enough to see its joints, a big one is
  // not held at full size in memory twice.
  const scale = PHOTO_SIDE / Math.max(width, height);
  canvas.width = Math.max(1, Math.round(width * scale));
  canvas.height = Math.max(1, Math.round(height * scale));
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#e8e8e4";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (state.picture) ctx.drawImage(state.picture, 0, 0, canvas.width, canvas.height);
  else if (!state.file) placeholder(ctx, canvas, "Your photo appears here");
  else if (!state.people.length) placeholder(ctx, canvas, "This browser cannot show the file");
  const size = Math.max(canvas.width, canvas.height);
  let joints = 0;
  const several = state.people.length > 1 || Array.isArray(state.answer?.people);
  for (const person of state.people) {
    if (several) drawFoundBox(ctx, person, scale, size);
    joints += drawSkeleton2d(ctx, person, scale, size);
  }
  if (state.box) drawUserBox(ctx, state.box, scale, size);
  // What was drawn, for tests and tools to check (not what was meant to be).
  canvas.dataset.joints = String(joints);
  canvas.dataset.people = String(state.people.length);
}

function placeholder(ctx, canvas, text) {
  ctx.fillStyle = "#6b6b66";
  ctx.font = `${Math.round(canvas.height / 16)}px system-ui, sans-serif`;
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  ctx.fillText(text, canvas.width / 2, canvas.height / 2);
}

// One person's limbs and joints; returns the number of joints drawn.
function drawSkeleton2d(ctx, person, scale, size) {
  const points = person.joints_2d.map(([x, y]) => [x * scale, y * scale]);
  const ok = (i) => points[i].every(Number.isFinite);
  ctx.lineCap = "round";
  for (const [child, parent] of SKELETON.limbs) {
    if (!ok(child) || !ok(parent)) continue;
    // a pale halo first, so that the limb shows on dark and light photos alike
    const strokes = [["rgba(255, 255, 255, 0.75)", 0.013], [SKELETON.colours[child], 0.008]];
    for (const [style, width] of strokes) {
      ctx.strokeStyle = style;
      ctx.lineWidth = Math.max(2, width * size);
      ctx.beginPath();
      ctx.moveTo(...points[child]);
      ctx.lineTo(...points[parent]);
      ctx.stroke();
    }
  }
  let drawn = 0;
  const radius = Math.max(3, 0.012 * size);
  points.forEach((point, i) => {
    if (!ok(i)) return;
    // white for a joint surely right, darker the less sure: its confidence is the probability
    // that it lies within PCK@0.2 of the truth (ds3d/viz/overlay.py's scheme)
    const sure = person.confidence?.[i] ?? 1;
    const shade = Math.round(255 * Math.min(Math.max(sure, 0), 1));
    ctx.fillStyle = `rgb(${shade}, ${shade}, ${shade})`;
    ctx.strokeStyle = "#111";
    ctx.lineWidth = Math.max(1, radius / 3);
    ctx.beginPath();
    ctx.arc(point[0], point[1], radius, 0, 2 * Math.PI);
    ctx.fill();
    ctx.stroke();
    drawn += 1;
  });
  return drawn;
}

function drawFoundBox(ctx, person, scale, size) {
  if (!person.box) return;
  const [x0, y0, x1, y1] = person.box.map((v) => v * scale);
  ctx.strokeStyle = "rgba(255, 255, 255, 0.9)";
  ctx.lineWidth = Math.max(1, 0.003 * size);
  ctx.setLineDash([]);
  ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
  const label = percent(person.score);
  const em = 0.04 * size; // the canvas is shown at a third or less of its size
  ctx.font = `${Math.round(em)}px system-ui, sans-serif`;
  ctx.textAlign = "left";
  ctx.textBaseline = "middle";
  const pad = 0.25 * em;
  const width = ctx.measureText(label).width + 2 * pad;
  const top = Math.max(0, y0 - 1.3 * em);
  ctx.fillStyle = "rgba(0, 0, 0, 0.6)";
  ctx.fillRect(x0, top, width, 1.3 * em);
  ctx.fillStyle = "#fff";
  ctx.fillText(label, x0 + pad, top + 0.65 * em);
}

function drawUserBox(ctx, box, scale, size) {
  const [x0, y0, x1, y1] = box.map((v) => v * scale);
  ctx.lineWidth = Math.max(2, 0.004 * size);
  // dashes in two colours: visible on any photo
  for (const [colour, offset] of [["#000", 0], ["#ffd400", 0.012 * size]]) {
    ctx.strokeStyle = colour;
    ctx.setLineDash([0.012 * size, 0.012 * size]);
    ctx.lineDashOffset = offset;
    ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
  }
  ctx.setLineDash([]);
}

// ---------------------------------------------------------------------------------------------
// The 3D view: canvas 2D and a perspective projection of our own.
//
// Every person where it stands: its joints in the camera's frame (joints_3d_camera: x right,
// y down, z away, mm). The view's world is y-up: X = x, Y = -y, Z = -z, moved so that the middle
// of the grid is the origin, the people standing on the ground (Y = 0) under the lowest joint;
// the axes read the camera's x and z. The grid reaches a little past the people and the eye
// stands as near as shows them and it (fitDistance): one person fills most of the view, and
// several people all show.

// The ground's ticks: the first step that labels its side in about 5 ticks; the grid at half
// of it. The height is ticked every HEIGHT_TICK_MM.
const TICKS_MM = [500, 1000, 2000, 5000, 10000];
const HEIGHT_TICK_MM = 500;
const GRID_MARGIN_MM = 150; // the grid's reach past the outermost joints (before its steps)
const FIELD_OF_VIEW = (25 * Math.PI) / 180; // narrow: little distortion near the eye
const NEAREST_MM = 1500; // the eye's distance, as near and as far as the zoom goes
const FARTHEST_MM = 30000;

function placeScene(people) {
  if (!people.length) return null;
  const joints = people.flatMap((person) => person.joints_3d_camera);
  const span = (k) => [Math.min(...joints.map((p) => p[k])), Math.max(...joints.map((p) => p[k]))];
  const [[xLow, xHigh], [zLow, zHigh]] = [span(0), span(2)];
  const half = Math.max(xHigh - xLow, zHigh - zLow) / 2 + GRID_MARGIN_MM;
  const tick = TICKS_MM.find((t) => half / t <= 2.5) ?? TICKS_MM[TICKS_MM.length - 1];
  const step = tick / 2;
  // the grid's edges (camera x and z): GRID_MARGIN_MM past the outermost joints, out to a line
  const edges = [
    [xLow, xHigh],
    [zLow, zHigh],
  ].map(([low, high]) => [
    Math.floor((low - GRID_MARGIN_MM) / step) * step,
    Math.ceil((high + GRID_MARGIN_MM) / step) * step,
  ]);
  const origin = edges.map(([low, high]) => (low + high) / 2); // the grid's centre
  const skeletons = people.map(({ joints_3d_camera: points }) =>
    points.map(([x, y, z]) => [x - origin[0], -y, -(z - origin[1])]),
  );
  const floor = Math.min(...skeletons.flat().map((p) => p[1]));
  for (const skeleton of skeletons) for (const p of skeleton) p[1] -= floor;
  return {
    skeletons,
    origin,
    tick,
    step,
    extentX: (edges[0][1] - edges[0][0]) / 2,
    extentZ: (edges[1][1] - edges[1][0]) / 2,
    height: Math.max(...skeletons.flat().map((p) => p[1])),
  };
}

// project([X, Y, Z]) -> [px, py, depth] for the current view, or null behind the eye.
function projector(canvas, scene, { yaw: yawDeg, pitch: pitchDeg, distance } = currentView()) {
  const yaw = (yawDeg * Math.PI) / 180;
  const pitch = (pitchDeg * Math.PI) / 180;
  const [cosY, sinY, cosP, sinP] = [Math.cos(yaw), Math.sin(yaw), Math.cos(pitch), Math.sin(pitch)];
  const focal = canvas.height / 2 / Math.tan(FIELD_OF_VIEW / 2);
  const centreY = (scene?.height ?? 1700) / 2; // the eye looks at the middle of the people
  return ([X, Y, Z]) => {
    const y = Y - centreY;
    // turn about the vertical axis (yaw), then tip towards the eye (pitch)
    const x1 = X * cosY + Z * sinY;
    const z1 = -X * sinY + Z * cosY;
    const y2 = y * cosP - z1 * sinP;
    const z2 = y * sinP + z1 * cosP;
    const depth = distance - z2;
    if (depth < 100) return null;
    return [canvas.width / 2 + (focal * x1) / depth, canvas.height / 2 - (focal * y2) / depth, depth];
  };
}

function currentView() {
  return { ...view, distance: view.distance ?? state.fit };
}

// The nearest eye distance, at the default angles, from which the people, the grid and the
// axes' numbers all show with a margin (the axes' titles are kept on the canvas where they are
// drawn, onCanvas): with the grid reaching a little past the people, they fill the view, small
// and big scenes, wide and narrow canvases alike.
function fitDistance(canvas, scene) {
  const { extentX: ex, extentZ: ez } = scene;
  const corners = [-ex, ex].flatMap((x) => [-ez, ez].map((z) => [x, 0, z]));
  const numbers = axisLabels(scene).labels.map(([p]) => p);
  const points = [...corners, ...numbers, ...scene.skeletons.flat()];
  const margin = 0.04 * Math.min(canvas.width, canvas.height); // labels reach past their point
  let distance = NEAREST_MM;
  while (distance < FARTHEST_MM) {
    const project = projector(canvas, scene, { ...DEFAULT_VIEW, distance });
    if (points.map(project).every((p) => p && inCanvas(canvas, p, margin))) break;
    distance *= 1.05;
  }
  return distance;
}

// Whether canvas px [x, y] lies inside the canvas, at least `margin` px from its edges.
function inCanvas(canvas, [x, y], margin = 0) {
  return x >= margin && x <= canvas.width - margin && y >= margin && y <= canvas.height - margin;
}

// The height axis's top: the tick nearest the people's height.
function axisTop(scene) {
  return Math.max(1, Math.round(scene.height / HEIGHT_TICK_MM)) * HEIGHT_TICK_MM;
}

function sizeCanvas3d(canvas) {
  // The canvas is as wide as its box (CSS), at the screen's pixel density.
  const ratio = window.devicePixelRatio || 1;
  const width = Math.max(1, Math.round(canvas.clientWidth * ratio));
  const height = Math.max(1, Math.round(canvas.clientHeight * ratio));
  if (canvas.width !== width || canvas.height !== height) {
    canvas.width = width;
    canvas.height = height;
    state.fit = state.scene ? fitDistance(canvas, state.scene) : state.fit;
  }
  return ratio;
}

function draw3d() {
  const canvas = $("view3d");
  const ratio = sizeCanvas3d(canvas);
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = BACKGROUND_3D;
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const scene = state.scene;
  canvas.dataset.yaw = String(view.yaw);
  canvas.dataset.pitch = String(view.pitch);
  canvas.dataset.distance = String(Math.round(currentView().distance));
  if (!scene) {
    placeholder(ctx, canvas, state.file ? "" : "The 3D pose appears here");
    canvas.dataset.joints = "0";
    return;
  }
  const project = projector(canvas, scene);
  const font = Math.round(12 * ratio);
  drawGrid(ctx, project, scene, ratio);
  drawAxes(ctx, project, scene, ratio, font);
  canvas.dataset.joints = String(drawSkeletons3d(ctx, project, scene, ratio));
}

function segment(ctx, a, b) {
  if (!a || !b) return;
  ctx.beginPath();
  ctx.moveTo(a[0], a[1]);
  ctx.lineTo(b[0], b[1]);
  ctx.stroke();
}

function drawGrid(ctx, project, scene, ratio) {
  const { extentX: ex, extentZ: ez } = scene;
  ctx.lineWidth = ratio;
  for (let x = -ex; x <= ex; x += scene.step) {
    ctx.strokeStyle = x === 0 ? "#a9a9a2" : "#d6d6d0";
    segment(ctx, project([x, 0, -ez]), project([x, 0, ez]));
  }
  for (let z = -ez; z <= ez; z += scene.step) {
    ctx.strokeStyle = z === 0 ? "#a9a9a2" : "#d6d6d0";
    segment(ctx, project([-ex, 0, z]), project([ex, 0, z]));
  }
}

// Axes ticked (scene.tick, HEIGHT_TICK_MM): x along the grid's front edge, z along its left edge, the height up
// from its back left corner (behind the people). x and z read as the camera's (x right, z away
// from it); the vertical one is the height above the lowest joint.
const LABEL_OFFSET_MM = 140; // labels stand off their axis

function axisLabels(scene) {
  const { extentX: ex, extentZ: ez } = scene;
  const top = axisTop(scene);
  const out = LABEL_OFFSET_MM;
  const labels = [];
  const { tick, origin: [x0, z0] } = scene;
  // the camera's x and z at the ticks within [low, high] of the grid, as [grid's, camera's]
  const ticks = (low, high, camera) =>
    Array.from({ length: Math.floor((high - low) / scene.step) + 1 }, (_, i) => low + i * scene.step)
      .map((at) => [at, camera(at)])
      .filter(([, value]) => value % tick === 0);
  // the corner's own tick is the z axis's: two numbers there would overlap
  for (const [x, value] of ticks(-ex, ex, (x) => x + x0).filter(([x]) => x > -ex)) {
    labels.push([[x, 0, ez + out], String(value)]);
  }
  for (const [z, value] of ticks(-ez, ez, (z) => z0 - z)) labels.push([[-ex - out, 0, z], String(value)]);
  for (let y = HEIGHT_TICK_MM; y <= top; y += HEIGHT_TICK_MM) {
    labels.push([[-ex - out, y, -ez - out], String(y)]);
  }
  const titles = [
    [[ex + 2.5 * out, 0, ez + out], "x (mm)"],
    [[-ex - out, 0, -ez - 2.5 * out], "z (mm)"], // past the far end, where z grows
    [[-ex, top + 1.5 * out, -ez], "height (mm)"],
  ];
  return { labels, titles };
}

function drawAxes(ctx, project, scene, ratio, font) {
  const { extentX: ex, extentZ: ez } = scene;
  ctx.strokeStyle = "#55554f";
  ctx.lineWidth = 1.5 * ratio;
  segment(ctx, project([-ex, 0, ez]), project([ex, 0, ez]));
  segment(ctx, project([-ex, 0, -ez]), project([-ex, 0, ez]));
  segment(ctx, project([-ex, 0, -ez]), project([-ex, axisTop(scene), -ez]));
  ctx.fillStyle = "#3d3d38";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  const { labels, titles } = axisLabels(scene);
  for (const [weight, list, keep] of [["", labels, false], ["bold ", titles, true]]) {
    ctx.font = `${weight}${font}px system-ui, sans-serif`;
    for (const [point, text] of list) {
      const p = project(point);
      if (p) ctx.fillText(text, ...(keep ? onCanvas(ctx, text, p, font) : p));
    }
  }
}

// Where to centre `text` near canvas px p so that all of it shows (font px high).
function onCanvas(ctx, text, [x, y], font) {
  const half = ctx.measureText(text).width / 2 + font / 2;
  const clamp = (v, low, high) => Math.min(Math.max(v, low), high);
  return [clamp(x, half, ctx.canvas.width - half), clamp(y, font, ctx.canvas.height - font)];
}

// Limbs far to near (painter's order), then the joints; returns the number of joints that show
// (drawn on the canvas).
function drawSkeletons3d(ctx, project, scene, ratio) {
  const limbs = [];
  const joints = [];
  for (const skeleton of scene.skeletons) {
    const points = skeleton.map(project);
    for (const [child, parent] of SKELETON.limbs) {
      const [a, b] = [points[child], points[parent]];
      if (a && b) limbs.push({ a, b, depth: (a[2] + b[2]) / 2, colour: SKELETON.colours[child] });
    }
    points.forEach((p, i) => p && joints.push({ p, depth: p[2], colour: SKELETON.colours[i] }));
  }
  const focal = ctx.canvas.height / 2 / Math.tan(FIELD_OF_VIEW / 2);
  ctx.lineCap = "round";
  for (const limb of limbs.sort((u, v) => v.depth - u.depth)) {
    ctx.strokeStyle = limb.colour;
    ctx.lineWidth = Math.max(2 * ratio, (focal * 35) / limb.depth); // a limb ~35 mm thick
    segment(ctx, limb.a, limb.b);
  }
  for (const joint of joints.sort((u, v) => v.depth - u.depth)) {
    ctx.fillStyle = joint.colour;
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = ratio;
    ctx.beginPath();
    ctx.arc(joint.p[0], joint.p[1], Math.max(2.5 * ratio, (focal * 30) / joint.depth), 0, 2 * Math.PI);
    ctx.fill();
    ctx.stroke();
  }
  return joints.filter(({ p }) => inCanvas(ctx.canvas, p)).length;
}

// Turning and zooming: one pointer (mouse, pen or finger) turns, two fingers pinch to zoom,
// the wheel and the keys do both without a pointer.

function turn(dYaw, dPitch) {
  view.yaw = (((view.yaw + dYaw) % 360) + 540) % 360 - 180; // kept in [-180, 180)
  view.pitch = Math.min(89, Math.max(-10, view.pitch + dPitch)); // never upside down
  draw3d();
}

function zoom(factor) {
  view.distance = Math.min(FARTHEST_MM, Math.max(NEAREST_MM, currentView().distance * factor));
  draw3d();
}

function resetView() {
  Object.assign(view, DEFAULT_VIEW);
  draw3d();
}

function wireView3d() {
  const canvas = $("view3d");
  const pointers = new Map(); // pointerId -> [x, y] of the pointers down
  const spread = () => {
    const [a, b] = [...pointers.values()];
    return Math.hypot(a[0] - b[0], a[1] - b[1]);
  };
  canvas.addEventListener("pointerdown", (event) => {
    capture(canvas, event);
    pointers.set(event.pointerId, [event.clientX, event.clientY]);
  });
  canvas.addEventListener("pointermove", (event) => {
    const last = pointers.get(event.pointerId);
    if (!last) return;
    const before = pointers.size === 2 ? spread() : 0;
    pointers.set(event.pointerId, [event.clientX, event.clientY]);
    if (pointers.size === 1) turn(0.4 * (event.clientX - last[0]), 0.4 * (event.clientY - last[1]));
    else if (pointers.size === 2 && before > 0) zoom(before / Math.max(1, spread()));
  });
  const lift = (event) => pointers.delete(event.pointerId);
  canvas.addEventListener("pointerup", lift);
  canvas.addEventListener("pointercancel", lift);
  // not passive: the wheel zooms the view instead of scrolling the page
  canvas.addEventListener("wheel", (event) => {
    event.preventDefault();
    zoom(Math.exp(event.deltaY * 0.0015));
  }, { passive: false });
  canvas.addEventListener("keydown", (event) => {
    const keys = {
      ArrowLeft: () => turn(-10, 0),
      ArrowRight: () => turn(10, 0),
      ArrowUp: () => turn(0, -5),
      ArrowDown: () => turn(0, 5),
      "+": () => zoom(1 / 1.15),
      "=": () => zoom(1 / 1.15),
      "-": () => zoom(1.15),
      _: () => zoom(1.15),
      0: resetView,
      Home: resetView,
    };
    const action = keys[event.key];
    if (!action || event.ctrlKey || event.metaKey || event.altKey) return;
    event.preventDefault(); // the arrows turn the view, not scroll the page
    action();
  });
  $("view-reset").addEventListener("click", resetView);
  // The canvas follows its CSS box (phone rotation, window resize).
  new ResizeObserver(() => draw3d()).observe(canvas);
}

// ---------------------------------------------------------------------------------------------

function main() {
  wireInputs();
  wireBoxDrag();
  wireView3d();
  $("download").addEventListener("click", download);
  draw2d();
  draw3d();
}

main();
