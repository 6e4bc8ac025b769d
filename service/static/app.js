// The web page's logic, plain JavaScript: a client of the service's public API like any other.
// One `POST /disparity?format=json` per run gives the float32 maps; the page colours them itself
// (the same colour maps and robust range as the service's `format=png`, stereo_data/visualize.py),
// so hovering can read the exact value at any pixel. Downloads send the pair again per format.
"use strict";

// Every `format` of POST /disparity (service/schemas.py OutputFormat), offered as downloads.
const FORMATS = [
  { format: "json", suffix: "maps.json", label: "json: float32 maps (base64)" },
  { format: "npz", suffix: "maps.npz", label: "npz: numpy arrays" },
  { format: "png", suffix: "preview.png", label: "png: colour preview" },
  { format: "disparity_png16", suffix: "disparity16.png", label: "disparity_png16: KITTI 16-bit" },
  { format: "uncertainty_png16", suffix: "uncertainty16.png", label: "uncertainty_png16: 16-bit" },
  { format: "depth_png16", suffix: "depth16.png", label: "depth_png16: KITTI depth 16-bit", needsCalibration: true },
  { format: "ply", suffix: "cloud.ply", label: "ply: point cloud" },
];

// A model this service serves that is not (yet) the one to use, with why and the one to use instead.
// GET /models says only whether weights are trained at all (`status`), not which model is ahead, so this
// is the one place where the page knows it. Remove `full` once its weights are properly trained and
// measured ahead of lite (README, the dev table: full's row against lite's defaults).
const NOT_RECOMMENDED = {
  full: {
    instead: "lite",
    why: "it has had only a short training of its own so far: it is no more accurate than lite on real pairs " +
      "(the README's table) and many times slower on a CPU",
  },
};

const state = {
  files: { left: null, right: null },  // File objects
  baseName: "pair",                    // stem of the download file names
  models: {},                          // name -> GET /models entry
  last: null,                          // { left, right, calibration, params, baseName, jsonText } of the result shown
  result: null,                        // { width, height, disparity, uncertainty, depth, leftAligned }
  calibrationFromExample: false,       // the calibration field holds the chosen example's file
};

const $ = (id) => document.getElementById(id);

/** An error answer of the service (status, its `code` and `message`), or a local failure. */
class ServiceError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

// --- talking to the service ------------------------------------------------------------------

/** The service's JSON error of a failed response, or its text when it is not JSON. */
async function errorFrom(response) {
  const text = await response.text();
  try {
    const body = JSON.parse(text);
    if (body && body.error && typeof body.error.message === "string") {
      return new ServiceError(response.status, body.error.code, body.error.message);
    }
  } catch (_) { /* not JSON: fall through */ }
  return new ServiceError(response.status, "http_error", text.slice(0, 500) || response.statusText);
}

/** fetch() that turns network failures and non-2xx answers into ServiceError. */
async function request(url, options) {
  let response;
  try {
    response = await fetch(url, options);
  } catch (err) {
    throw new ServiceError(0, "network_error", `could not reach the service (${err.message})`);
  }
  if (!response.ok) throw await errorFrom(response);
  return response;
}

const API_KEY = "crestereo-api-key";  // sessionStorage: the key stays for this tab's session only

/** The `Authorization` header of the API key entered (none when the field is empty). */
function authorization() {
  const key = $("api-key").value.trim();
  return key ? { Authorization: `Bearer ${key}` } : {};
}

/** POST /disparity with the pair, its calibration files (none for a rectified pair), the options
 * `params` (URLSearchParams) and `format`. */
function postDisparity(left, right, calibration, params, format) {
  const form = new FormData();
  form.append("left", left, left.name);
  form.append("right", right, right.name);
  for (const file of calibration) form.append("calibration", file, file.name);
  const query = new URLSearchParams(params);
  query.set("format", format);
  return request(`disparity?${query}`, { method: "POST", body: form, headers: authorization() });
}

/** The calibration files chosen: none, one OpenCV file, or the left and right ROS camera_info. */
function readCalibration() {
  return ["calibration-file", "calibration-right-file"].map((id) => $(id).files[0]).filter(Boolean);
}

/** The query options from the form: every named control, empty ones and checkboxes at their
 * default (the service's) left out (and `frame` only with a calibration, the one case where it
 * means something). */
function readOptions(calibrated) {
  const params = new URLSearchParams();
  for (const element of $("options").elements) {
    if (!element.name || (element.name === "frame" && !calibrated)) continue;
    if (element.type === "checkbox") {
      if (element.checked !== element.defaultChecked) params.set(element.name, String(element.checked));
    } else if (element.value.trim() !== "") {
      params.set(element.name, element.value.trim());
    }
  }
  return params;
}

/** An EncodedArray of the JSON answer as a Float32Array (little-endian float32, row-major). */
function decodeArray(encoded, name) {
  if (!encoded || encoded.dtype !== "float32" || encoded.byte_order !== "little") {
    throw new ServiceError(0, "bad_answer", `${name}: expected little-endian float32`);
  }
  const bytes = Uint8Array.from(atob(encoded.data), (c) => c.charCodeAt(0));
  const [height, width] = encoded.shape;
  if (bytes.length !== height * width * 4) {
    throw new ServiceError(0, "bad_answer", `${name}: ${bytes.length} bytes for shape ${height}x${width}`);
  }
  const view = new DataView(bytes.buffer);
  const values = new Float32Array(height * width);
  for (let i = 0; i < values.length; i++) values[i] = view.getFloat32(4 * i, true);
  return values;
}

// --- colours, ranges, colour bars ------------------------------------------------------------

/** Linear-interpolated percentile of sorted values, as numpy.percentile computes it. */
function percentile(sorted, p) {
  const position = (sorted.length - 1) * p / 100;
  const low = Math.floor(position);
  const high = Math.min(low + 1, sorted.length - 1);
  return sorted[low] + (sorted[high] - sorted[low]) * (position - low);
}

/** stereo_data.visualize.scale_range: the given ends, else the 1st-99th percentile. */
function scaleRange(values, low, high) {
  const finite = Float32Array.from(values.filter(Number.isFinite)).sort();
  let robustLow = 0, robustHigh = 1;
  if (finite.length > 0) {
    robustLow = percentile(finite, 1);
    robustHigh = percentile(finite, 99);
    if (robustHigh - robustLow < 1e-3) robustHigh = robustLow + 1e-3;
  }
  const bottom = low ?? robustLow;
  const top = high ?? Math.max(robustHigh, bottom + 1e-3);
  return [bottom, top];
}

/** Paint `values` into `canvas` through a 256-entry RGB table over [vmin, vmax]; non-finite black. */
function paintMap(canvas, values, width, height, vmin, vmax, table) {
  canvas.width = width;
  canvas.height = height;
  const context = canvas.getContext("2d");
  const image = context.createImageData(width, height);
  const span = Math.max(vmax - vmin, 1e-6);
  for (let i = 0; i < values.length; i++) {
    const value = values[i];
    const o = 4 * i;
    image.data[o + 3] = 255;
    if (!Number.isFinite(value)) continue;
    const k = 3 * Math.round(Math.min(Math.max((value - vmin) / span, 0), 1) * 255);
    image.data[o] = table[k];
    image.data[o + 1] = table[k + 1];
    image.data[o + 2] = table[k + 2];
  }
  context.putImageData(image, 0, 0);
}

/** A number with 3 significant digits, as the service's colour bars print them (%.3g). */
function g3(value) {
  return String(Number(value.toPrecision(3)));
}

/** Fill a colour bar: gradient, the low/middle/high values with their unit, a caption. */
function paintBar(bar, vmin, vmax, table, unit, caption) {
  const gradient = bar.querySelector(".bar-gradient");
  const context = gradient.getContext("2d");
  const image = context.createImageData(256, 1);
  for (let k = 0; k < 256; k++) {
    image.data.set([table[3 * k], table[3 * k + 1], table[3 * k + 2], 255], 4 * k);
  }
  context.putImageData(image, 0, 0);
  const suffix = unit ? ` ${unit}` : "";
  bar.querySelector(".low").textContent = g3(vmin) + suffix;
  bar.querySelector(".mid").textContent = g3((vmin + vmax) / 2) + suffix;
  bar.querySelector(".high").textContent = g3(vmax) + suffix;
  bar.querySelector(".bar-caption").textContent = caption;
}

// --- showing a result ------------------------------------------------------------------------

/** Draw the left image file at the maps' size (a grey panel if the browser cannot decode it). */
async function paintLeft(file, width, height) {
  const canvas = $("left-canvas");
  canvas.width = width;
  canvas.height = height;
  const context = canvas.getContext("2d");
  try {
    const bitmap = await createImageBitmap(file);
    context.drawImage(bitmap, 0, 0, width, height);
    bitmap.close();
  } catch (_) {
    context.fillStyle = "#ccc";
    context.fillRect(0, 0, width, height);
    context.fillStyle = "#333";
    context.fillText("this browser cannot display the file", 6, 16);
  }
}

function optionNumber(params, name) {
  return params.has(name) ? Number(params.get(name)) : undefined;
}

/** What the summary says of the right image's rows: the offset the service measured on the pair
 * (`row_offset`), or nothing where `align_rows` was turned off. */
function rowsSummary(params, offset) {
  if (params.get("align_rows") === "false") return "";
  if (!offset) return " · rows: too little texture to measure their offset";
  const largest = `${offset.largest_px.toFixed(2)} px`;
  return offset.aligned
    ? ` · rows off the left's by up to ${largest}, aligned before matching` +
      (offset.largest_px >= 1 ? " (check the rig's calibration)" : "")
    : ` · rows on the left's (within ${largest})`;
}

async function showResult(body, params, left) {
  const [height, width] = body.disparity.shape;
  const result = {
    width, height,
    disparity: decodeArray(body.disparity, "disparity"),
    uncertainty: decodeArray(body.uncertainty, "uncertainty"),
    depth: body.depth ? decodeArray(body.depth, "depth") : null,
    // The left panel draws the file as uploaded: the maps' pixels are its pixels unless they are in
    // the rectified image of a raw pair (frame=rectified), which the page cannot draw.
    leftAligned: !(body.camera && body.frame === "rectified"),
  };
  const colorMin = optionNumber(params, "color_min");
  const colorMax = optionNumber(params, "color_max");
  const [low, high] = scaleRange(result.disparity, colorMin, colorMax);
  paintMap($("disparity-canvas"), result.disparity, width, height, low, high, COLORMAPS.turbo);
  paintMap($("uncertainty-canvas"), result.uncertainty, width, height, 0, 1, COLORMAPS.inferno);
  const fixed = colorMin !== undefined || colorMax !== undefined;
  paintBar($("disparity-bar"), low, high, COLORMAPS.turbo, "px",
    `disparity in px of the left image; colour scale ${fixed ? "from color_min/color_max" : "over the map's 1st-99th percentile"}`);
  const model = state.models[body.model];
  const meaning = params.has("raw_uncertainty")
    ? "the paper's raw U (last iteration)" : (model ? model.uncertainty : "uncertainty");
  paintBar($("uncertainty-bar"), 0, 1, COLORMAPS.inferno, "", `uncertainty: ${meaning}; scale 0-1`);
  await paintLeft(left, width, height);
  $("left-caption").textContent = result.leftAligned ? "Left image" : "Left image (not rectified)";
  $("left-note").hidden = result.leftAligned;
  state.result = result;
  const untrained = body.model_status === "untrained";
  const warning = untrained ? untrainedWarning(body.model) : notRecommendedWarning(body.model);
  $("result-warning").hidden = warning === "";
  $("result-warning").textContent = warning;
  $("summary").textContent = `${body.model}${untrained ? " (untrained: maps not usable)" : ""}, ` +
    `weights ${body.weights} · ${width}x${height} px · ` +
    `batch of ${body.batch_size} · queued ${body.timings.queue_ms} ms · computed in ${body.timings.compute_ms} ms` +
    ` · disparity ${g3(low)}-${g3(high)} px (colour range)` +
    (body.camera ? ` · raw pair, rectified by its calibration (f ${g3(body.camera.focal_px)} px, baseline ` +
      `${g3(body.camera.baseline_m)} m); maps in the ${body.frame} left image` : "") +
    rowsSummary(params, body.row_offset);
  $("readout").textContent = "hover over an image for the values at that pixel";
  renderDownloads(result.depth !== null);
  $("results").hidden = false;
  $("results").scrollIntoView({ block: "start" });  // below the form on most screens: bring it into view
}

/** The values under the mouse, in the readout line. */
function hover(event) {
  const result = state.result;
  if (!result) return;
  if (event.currentTarget.id === "left-canvas" && !result.leftAligned) {
    $("readout").textContent = "the left image is shown as uploaded, not rectified: hover over a map for its values";
    return;
  }
  const rect = event.currentTarget.getBoundingClientRect();
  const x = Math.min(result.width - 1, Math.max(0, Math.floor((event.clientX - rect.left) / rect.width * result.width)));
  const y = Math.min(result.height - 1, Math.max(0, Math.floor((event.clientY - rect.top) / rect.height * result.height)));
  const i = y * result.width + x;
  const disparity = result.disparity[i];
  if (!Number.isFinite(disparity)) {  // frame=original: this camera pixel has no rectified counterpart
    $("readout").textContent = `x ${x}, y ${y} · no value: outside the rectified image`;
    return;
  }
  const parts = [`x ${x}, y ${y}`, `disparity ${disparity.toFixed(2)} px`, `uncertainty ${result.uncertainty[i].toFixed(3)}`];
  if (result.depth) {
    const depth = result.depth[i];
    parts.push(Number.isFinite(depth) ? `depth ${depth.toPrecision(4)} m` : "depth invalid (disparity too small)");
  } else {
    parts.push("depth: give a calibration file, or focal_px and baseline_m");
  }
  $("readout").textContent = parts.join(" · ");
}

// --- downloads -------------------------------------------------------------------------------

function save(blob, filename) {
  const url = URL.createObjectURL(blob);
  const link = document.createElement("a");
  link.href = url;
  link.download = filename;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}

function renderDownloads(calibrated) {
  const list = $("download-list");
  list.replaceChildren();
  for (const entry of FORMATS) {
    const item = document.createElement("li");
    const button = document.createElement("button");
    button.type = "button";
    button.textContent = entry.label;
    button.dataset.format = entry.format;
    if (entry.needsCalibration && !calibrated) {
      button.disabled = true;
      button.title = "needs a calibration file, or focal_px and baseline_m";
    }
    button.addEventListener("click", () => download(entry, button));
    item.append(button);
    list.append(item);
  }
}

async function download(entry, button) {
  const last = state.last;
  if (!last) return;
  clearError();
  const filename = `${last.baseName}_${entry.suffix}`;
  if (entry.format === "json") {  // the answer shown is already this format
    save(new Blob([last.jsonText], { type: "application/json" }), filename);
    return;
  }
  button.disabled = true;
  setStatus(`preparing ${entry.format}…`);
  try {
    const response = await postDisparity(last.left, last.right, last.calibration, last.params, entry.format);
    save(await response.blob(), filename);
    setStatus(`saved ${filename}`);
  } catch (err) {
    showError(err);
    setStatus("");
  } finally {
    button.disabled = false;
  }
}

// --- the form --------------------------------------------------------------------------------

function setStatus(text) {
  $("status").textContent = text;
}

function clearError() {
  $("error").hidden = true;
  $("error").textContent = "";
}

function showError(err) {
  const box = $("error");
  if (err instanceof ServiceError) {
    box.textContent = err.status ? `${err.status} ${err.code}: ${err.message}` : `${err.code}: ${err.message}`;
  } else {
    box.textContent = `error: ${err && err.message ? err.message : err}`;
  }
  box.hidden = false;
}

async function run(event) {
  event.preventDefault();
  clearError();
  const { left, right } = state.files;
  if (!left || !right) {
    showError(new ServiceError(0, "missing_image", "choose a left and a right image (or an example pair)"));
    return;
  }
  const calibration = readCalibration();
  const params = readOptions(calibration.length > 0);
  $("run").disabled = true;
  setStatus("computing…");
  const started = performance.now();
  try {
    const response = await postDisparity(left, right, calibration, params, "json");
    const jsonText = await response.text();
    const body = JSON.parse(jsonText);
    state.last = { left, right, calibration, params, baseName: state.baseName, jsonText };
    await showResult(body, params, left);
    setStatus(`done in ${Math.round(performance.now() - started)} ms`);
  } catch (err) {
    $("results").hidden = true;
    state.result = null;
    state.last = null;
    showError(err);
    setStatus("");
  } finally {
    $("run").disabled = false;
  }
}

function setFile(side, file, displayName) {
  state.files[side] = file;
  $(`${side}-name`).textContent = displayName || file.name;
  const thumb = $(`${side}-thumb`);
  if (thumb.src) URL.revokeObjectURL(thumb.src);
  thumb.src = URL.createObjectURL(file);
  thumb.hidden = false;
  if (side === "left") state.baseName = (displayName || file.name).replace(/\.[^.]*$/, "").replace(/[^\w.-]+/g, "_");
}

/** Two files dropped at once: the one named like "right" goes right, else in order. */
function assignDropped(side, files) {
  if (files.length >= 2) {
    const sorted = [...files].slice(0, 2);
    if (/right/i.test(sorted[0].name) && !/right/i.test(sorted[1].name)) sorted.reverse();
    setFile("left", sorted[0]);
    setFile("right", sorted[1]);
  } else if (files.length === 1) {
    setFile(side, files[0]);
  }
  $("example").value = "";
  if (state.calibrationFromExample) setCalibration(null);  // the example's calibration is not for these files
}

/** Put an example's calibration file into the calibration field, or empty the field (null). */
function setCalibration(file) {
  const transfer = new DataTransfer();
  if (file) transfer.items.add(file);
  $("calibration-file").files = transfer.files;
  $("calibration-right-file").value = "";
  state.calibrationFromExample = Boolean(file);
}

function wireDropZone(side) {
  const zone = $(`${side}-drop`);
  const input = $(`${side}-file`);
  input.addEventListener("change", () => assignDropped(side, input.files));
  zone.addEventListener("dragover", (event) => { event.preventDefault(); zone.classList.add("dragging"); });
  zone.addEventListener("dragleave", () => zone.classList.remove("dragging"));
  zone.addEventListener("drop", (event) => {
    event.preventDefault();
    zone.classList.remove("dragging");
    assignDropped(side, event.dataTransfer.files);
  });
}

async function loadExample() {
  const name = $("example").value;
  const entry = state.examples.find((example) => example.name === name);
  if (!entry) return;
  clearError();
  try {
    for (const side of ["left", "right"]) {
      const response = await request(`static/${entry[side]}`);
      const file = new File([await response.blob()], `${side}.png`, { type: "image/png" });
      setFile(side, file, `${name}/${side}.png`);
    }
    let calibration = null;  // a raw example's calibration, in the calibration field like a chosen file
    if (entry.calibration) {
      const response = await request(`static/${entry.calibration}`);
      const fileName = entry.calibration.split("/").pop();
      calibration = new File([await response.blob()], fileName, { type: "application/json" });
    }
    setCalibration(calibration);
    state.baseName = name;
    setStatus(`example ${name} loaded` + (calibration ? `, with its calibration ${calibration.name}` : ""));
  } catch (err) {
    showError(err);
  }
}

async function loadExamples() {
  state.examples = [];
  try {
    const response = await request("static/examples/examples.json");
    state.examples = (await response.json()).examples;
  } catch (err) {
    showError(err);
    return;
  }
  for (const example of state.examples) {
    const option = document.createElement("option");
    option.value = example.name;
    option.textContent = example.title;
    $("example").append(option);
  }
}

/** The warning for untrained weights of model `name`, naming the trained models loaded (the
 * recommended ones first), or saying that there is none. */
function untrainedWarning(name) {
  const trained = Object.values(state.models).filter((model) => model.status === "trained");
  const recommended = trained.filter((model) => !NOT_RECOMMENDED[model.name]);
  const choices = (recommended.length > 0 ? recommended : trained).map((model) => model.name);
  const advice = choices.length > 0
    ? `Choose a trained model (${choices.join(" or ")}) for real results.`
    : "No trained model is loaded on this server: it needs trained weights for real results.";
  return `${name} is untrained: its weights have not learned to match yet, and its maps are not usable. ${advice}`;
}

/** What the page says of model `name` where it is not the one to use (NOT_RECOMMENDED), else "". */
function notRecommendedWarning(name) {
  const note = NOT_RECOMMENDED[name];
  if (!note) return "";
  const loaded = state.models[note.instead] ? "" : " (not loaded on this server)";
  return `${name} is not the recommended model: ${note.why}. Use ${note.instead}${loaded}.`;
}

/** The chosen model's facts, and its warning: untrained, or not the recommended model. The training
 * record's dev numbers are not shown: each was measured at the model's own last validation, not
 * comparable across models (the README's table compares them). */
function describeModel() {
  const model = state.models[$("model").value];
  if (!model) return;
  $("iters").placeholder = model.iterations.join(",");
  const warning = $("model-warning");
  warning.textContent = model.status === "untrained" ? untrainedWarning(model.name) : notRecommendedWarning(model.name);
  warning.hidden = warning.textContent === "";
  $("model-info").textContent = `${model.parameters.toLocaleString("en")} parameters · iterations ` +
    `${model.iterations.join("/")} · up to ${model.max_image_pixels.toLocaleString("en")} pixels · ` +
    `uncertainty: ${model.uncertainty}`;
}

/** GET /models into the model list; retried while the service is still loading, or until the
 * API key it asks for is entered. */
async function loadModels() {
  let models = [];
  try {
    models = (await (await request("models", { headers: authorization() })).json()).models;
  } catch (err) {
    const hint = err.status === 401 ? "enter the service's API key under Access" : err.message;
    $("model-info").textContent = `cannot list the models: ${hint}; retrying…`;
  }
  if (models.length === 0) {
    if (!$("model-info").textContent.startsWith("cannot")) $("model-info").textContent = "models are loading; retrying…";
    setTimeout(loadModels, 2000);
    return;
  }
  const select = $("model");
  select.replaceChildren();
  for (const model of models) {
    state.models[model.name] = model;
    const option = document.createElement("option");
    option.value = model.name;
    let status = "";
    if (model.status === "untrained") status = ", untrained";
    else if (NOT_RECOMMENDED[model.name]) status = ", not recommended";
    option.textContent = `${model.name} (weights ${model.versions[0]}${status})`;
    select.append(option);
  }
  describeModel();
}

function main() {
  // a file dropped beside the drop zones must not navigate away from the page
  window.addEventListener("dragover", (event) => event.preventDefault());
  window.addEventListener("drop", (event) => event.preventDefault());
  wireDropZone("left");
  wireDropZone("right");
  $("example").addEventListener("change", loadExample);
  $("model").addEventListener("change", describeModel);
  $("options").addEventListener("submit", run);
  $("api-key").value = sessionStorage.getItem(API_KEY) ?? "";
  $("api-key").addEventListener("input", () => sessionStorage.setItem(API_KEY, $("api-key").value.trim()));
  for (const id of ["left-canvas", "disparity-canvas", "uncertainty-canvas"]) {
    $(id).addEventListener("mousemove", hover);
  }
  loadModels();
  loadExamples();
}

main();
