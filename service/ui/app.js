/* lightfield web page: upload, follow a job, place probes, look at and download the light.
 *
 * Plain JS, no build step. Every request goes through `api()`, which adds the API key as an
 * `Authorization: Bearer` header; the key is never put in a URL. Images are therefore
 * fetched with fetch() and shown through blob: URLs, and the job's Server-Sent Events are
 * read from a streamed fetch() (EventSource cannot send headers).
 *
 * Endpoints used: POST /jobs, GET /jobs, GET /jobs/{id}, GET /jobs/{id}/events, DELETE /jobs/{id},
 * GET /lightfield/{id} (+ /capture, /frame, /probe, /insertion, /envmap, /sh, /cubemap).
 */
"use strict";

(() => {
  const KEY_STORAGE = "lightfield.apiKey";
  const ENVMAP_VIEW_HEIGHT = 128; // 256 x 128 for the on-page preview
  const ENVMAP_DOWNLOAD_HEIGHT = 256;
  const CUBEMAP_DOWNLOAD_SIZE = 128;
  const AUTO_EXPOSURE_HEIGHT = 32;
  const AUTO_EXPOSURE_PERCENTILE = 0.99;
  const AUTO_EXPOSURE_TARGET = 0.85; // display value the percentile maps to
  const GAMMA = 2.4; // core.conventions: ldr = clip((2^ev L)^(1/2.4), 0, 1)
  const EV_RANGE = [-12, 12];
  const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);
  const STALE = Symbol("stale");

  const $ = (id) => document.getElementById(id);

  // ------------------------------------------------------------------ API access
  const auth = { key: sessionStorage.getItem(KEY_STORAGE) || "" };

  class ApiError extends Error {
    constructor(status, code, message) {
      super(message);
      this.status = status;
      this.code = code;
    }
  }

  async function api(path, options = {}) {
    const headers = new Headers(options.headers || {});
    if (auth.key) headers.set("Authorization", `Bearer ${auth.key}`);
    const response = await fetch(path, { ...options, headers });
    if (!response.ok) {
      let code = `http_${response.status}`;
      let message = response.statusText || `HTTP ${response.status}`;
      try {
        const body = await response.json();
        if (body && body.error) ({ code, message } = body.error);
      } catch (_) { /* not JSON */ }
      if (response.status === 401) {
        keyStatus(auth.key ? "key rejected" : "API key required", "bad");
        if (!auth.key) $("api-key").focus();
      }
      throw new ApiError(response.status, code, message);
    }
    return response;
  }

  const apiJson = async (path, options) => (await api(path, options)).json();
  const query = (params) => new URLSearchParams(params).toString();

  /** Run `fn` in a slot where only the latest call may deliver: older results throw STALE. */
  function latestOnly() {
    let seq = 0;
    return async (fn) => {
      const mine = ++seq;
      const value = await fn();
      if (mine !== seq) throw STALE;
      return value;
    };
  }

  const blobUrls = new WeakMap();
  /** Show a blob in an <img>, revoking the URL it replaces; resolves once decoded. */
  function showBlob(img, blob, key) {
    const url = URL.createObjectURL(blob);
    const previous = blobUrls.get(img);
    blobUrls.set(img, url);
    return new Promise((resolve) => {
      img.onload = img.onerror = () => {
        if (previous) URL.revokeObjectURL(previous);
        img.dataset.key = key;
        resolve();
      };
      img.src = url;
    });
  }

  function reportError(error) {
    if (error === STALE || (error && error.name === "AbortError")) return;
    if (error instanceof ApiError && error.status === 401) return; // shown next to the key field
    console.error(error);
    const toast = $("toast");
    toast.textContent = error instanceof ApiError ? `${error.message} (${error.code})` : String(error.message || error);
    toast.hidden = false;
    clearTimeout(reportError.timer);
    reportError.timer = setTimeout(() => { toast.hidden = true; }, 6000);
  }

  // ------------------------------------------------------------------ API key
  function keyStatus(text, kind = "") {
    const el = $("key-status");
    el.textContent = text;
    el.className = `key-status ${kind}`;
  }

  async function useKey(event) {
    event.preventDefault();
    auth.key = $("api-key").value.trim();
    if (auth.key) sessionStorage.setItem(KEY_STORAGE, auth.key);
    else sessionStorage.removeItem(KEY_STORAGE);
    try {
      await api("/jobs?limit=1");
      keyStatus(auth.key ? "key accepted" : "no key needed", "ok");
      refreshJobs();
      if (linkedJob() && linkedJob() !== view.id) openJob(linkedJob()).catch(reportError);
    } catch (error) {
      if (!(error instanceof ApiError && error.status === 401)) reportError(error);
      else keyStatus("key rejected", "bad");
    }
  }

  // ------------------------------------------------------------------ formatting
  const fmt = {
    seconds(s) {
      if (s == null || !isFinite(s)) return "—";
      if (s < 60) return `${Math.max(0, Math.round(s))} s`;
      const m = Math.floor(s / 60);
      return m < 60 ? `${m} min ${Math.round(s - 60 * m)} s` : `${Math.floor(m / 60)} h ${m % 60} min`;
    },
    loss: (v) => (v == null || !isFinite(v) ? "—" : v < 1e-3 ? v.toExponential(2) : v.toPrecision(3)),
    metres: (v) => (v == null ? "—" : `${v.toFixed(v < 10 ? 2 : 1)} m`),
    time: (t) => `t = ${t.toFixed(3)} s`,
    vec: (x) => x.map((c) => (Math.abs(c) < 0.005 ? 0 : c).toFixed(2)).join(", "),
    when(iso) {
      const d = new Date(iso);
      return isNaN(d) ? "" : d.toLocaleString(undefined, { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" });
    },
  };

  // ------------------------------------------------------------------ loss chart
  const lossChart = {
    points: [], // [iteration, loss]
    reset(points = []) { this.points = points; this.draw(); },
    add(iteration, loss) {
      if (loss == null || !isFinite(loss)) return;
      const last = this.points[this.points.length - 1];
      if (last && last[0] === iteration) last[1] = loss;
      else this.points.push([iteration, loss]);
      this.draw();
    },
    draw() {
      const canvas = $("loss-chart");
      const ratio = window.devicePixelRatio || 1;
      const w = canvas.clientWidth || 300;
      const h = canvas.clientHeight || 120;
      canvas.width = Math.round(w * ratio);
      canvas.height = Math.round(h * ratio);
      const g = canvas.getContext("2d");
      g.setTransform(ratio, 0, 0, ratio, 0, 0);
      g.clearRect(0, 0, w, h);
      g.font = "11px system-ui, sans-serif";
      g.fillStyle = "#9098a5";
      const pts = this.points.filter(([, l]) => l > 0);
      if (pts.length < 2) {
        g.fillText("loss curve appears once distillation starts", 10, h / 2 + 4);
        return;
      }
      const pad = { l: 44, r: 10, t: 10, b: 20 };
      const xs = pts.map((p) => p[0]);
      const ys = pts.map((p) => Math.log10(p[1]));
      const x0 = Math.min(...xs), x1 = Math.max(...xs, x0 + 1);
      let y0 = Math.min(...ys), y1 = Math.max(...ys);
      if (y1 - y0 < 1e-6) { y0 -= 0.5; y1 += 0.5; }
      const px = (x) => pad.l + ((x - x0) / (x1 - x0)) * (w - pad.l - pad.r);
      const py = (y) => pad.t + (1 - (y - y0) / (y1 - y0)) * (h - pad.t - pad.b);
      g.strokeStyle = "#2e333b";
      g.lineWidth = 1;
      for (let k = 0; k <= 2; k++) {
        const y = y0 + ((y1 - y0) * k) / 2;
        g.beginPath(); g.moveTo(pad.l, py(y)); g.lineTo(w - pad.r, py(y)); g.stroke();
        g.fillText(fmt.loss(10 ** y), 4, py(y) + 4);
      }
      g.fillText(`step ${x1}`, w - pad.r - 52, h - 5);
      g.fillText("log loss", pad.l, h - 5);
      g.strokeStyle = "#f5b942";
      g.lineWidth = 1.6;
      g.beginPath();
      pts.forEach(([x], i) => (i ? g.lineTo(px(x), py(ys[i])) : g.moveTo(px(x), py(ys[i]))));
      g.stroke();
    },
  };

  // ------------------------------------------------------------------ job progress (SSE over fetch)
  const job = { id: null, controller: null };

  function parseEvent(block) {
    let event = "message";
    const data = [];
    for (const line of block.split(/\r?\n/)) {
      if (!line || line.startsWith(":")) continue;
      const i = line.indexOf(":");
      const field = i < 0 ? line : line.slice(0, i);
      let value = i < 0 ? "" : line.slice(i + 1);
      if (value.startsWith(" ")) value = value.slice(1);
      if (field === "event") event = value;
      else if (field === "data") data.push(value);
    }
    return data.length ? { event, data: data.join("\n") } : null;
  }

  async function streamEvents(path, onEvent, signal) {
    const response = await api(path, { signal, headers: { Accept: "text/event-stream" } });
    const reader = response.body.getReader();
    const decoder = new TextDecoder();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buffer += decoder.decode(value, { stream: true });
      let match;
      while ((match = /\r?\n\r?\n/.exec(buffer))) {
        const parsed = parseEvent(buffer.slice(0, match.index));
        buffer = buffer.slice(match.index + match[0].length);
        if (parsed) onEvent(parsed);
      }
    }
  }

  function showJob(record) {
    $("progress-card").hidden = false;
    const state = $("job-state");
    state.textContent = record.state;
    state.dataset.state = record.state;
    // floor: "100 %" only once the job has really succeeded
    const pct = record.state === "succeeded" ? 100 : Math.min(99, Math.floor(100 * (record.progress || 0)));
    $("progress-fill").style.width = `${pct}%`;
    $("progress-bar").setAttribute("aria-valuenow", String(pct));
    $("progress-percent").textContent = `${pct} %`;
    $("progress-stage").textContent = record.stage || record.state;
    $("progress-iteration").textContent = record.total ? `${record.iteration} / ${record.total}` : "—";
    $("progress-loss").textContent = fmt.loss(record.loss);
    $("progress-eta").textContent = TERMINAL.has(record.state) ? "—" : fmt.seconds(record.eta_s);
    $("job-message").textContent = TERMINAL.has(record.state) ? "" : record.message || "";
    const error = $("job-error");
    error.hidden = !record.error;
    error.textContent = record.error ? `${record.error.message} (${record.error.code})` : "";
    $("cancel-button").hidden = TERMINAL.has(record.state);
    if (record.stage === "distill" && record.iteration > 0) lossChart.add(record.iteration, record.loss);
  }

  async function watchJob(id) {
    if (job.controller) job.controller.abort();
    const controller = new AbortController();
    Object.assign(job, { id, controller });
    lossChart.reset();
    markCurrentJob();
    let current = await apiJson(`/jobs/${id}`, { signal: controller.signal });
    showJob(current);
    // The stream ends when the job ends; a dropped connection is resumed after a pause.
    while (!TERMINAL.has(current.state) && !controller.signal.aborted) {
      try {
        await streamEvents(`/jobs/${id}/events`, (ev) => {
          if (ev.event === "job") { current = JSON.parse(ev.data); showJob(current); }
        }, controller.signal);
      } catch (error) {
        if (controller.signal.aborted) return;
        if (error instanceof ApiError && error.status === 404) throw error;
        await new Promise((r) => setTimeout(r, 1000));
      }
      if (!TERMINAL.has(current.state) && !controller.signal.aborted) {
        current = await apiJson(`/jobs/${id}`, { signal: controller.signal });
        showJob(current);
      }
    }
    if (controller.signal.aborted) return;
    refreshJobs();
    if (current.state === "succeeded") await openResult(id);
  }

  async function cancelJob() {
    if (!job.id) return;
    try {
      await api(`/jobs/${job.id}`, { method: "DELETE" });
    } catch (error) { reportError(error); }
  }

  // ------------------------------------------------------------------ upload
  let pendingUrl = null;
  /** Show the file being estimated (from the local disk, nothing is downloaded). */
  function showPending(file) {
    if (pendingUrl) URL.revokeObjectURL(pendingUrl);
    pendingUrl = file ? URL.createObjectURL(file) : null;
    const box = $("pending-media");
    box.replaceChildren();
    $("pending").hidden = !file;
    if (!file) return;
    $("empty-state").hidden = true;
    $("pending-name").textContent = file.name;
    const media = document.createElement(file.type.startsWith("video/") ? "video" : "img");
    if (media.tagName === "VIDEO") Object.assign(media, { muted: true, loop: true, autoplay: true, playsInline: true });
    media.src = pendingUrl;
    box.append(media);
  }

  // Files uploaded from this tab, by job id: "Re-estimate" with a corrected FOV sends them again
  // (the service deletes a job's uploads once it has succeeded).
  const uploads = new Map();

  function jobParams() {
    const params = { preset: $("preset-input").value, temporal: $("temporal-input").value };
    const fps = parseFloat($("fps-input").value);
    const hfov = parseFloat($("hfov-input").value);
    if (isFinite(fps)) params.fps = fps;
    if (isFinite(hfov)) params.intrinsics = { hfov_deg: hfov };
    return params;
  }

  async function submitUpload(event) {
    event.preventDefault();
    const file = $("file-input").files[0];
    const depth = $("depth-input").files[0];
    const error = $("upload-error");
    const button = $("upload-button");
    error.hidden = true;
    if (!file) { error.textContent = "Choose an image, a video or a capture zip first."; error.hidden = false; return; }
    button.disabled = true;
    button.textContent = "Uploading…";
    try {
      await submitJob(file, depth, jobParams());
    } catch (e) {
      error.textContent = e instanceof ApiError ? e.message : `Upload failed: ${e.message}`;
      error.hidden = false;
    } finally {
      button.disabled = false;
      button.textContent = "Estimate lighting";
    }
  }

  /** The bundled sample: a room scan rendered by the service (GET /samples/room_scan.mp4),
   * uploaded as a user's own video would be, with no poses or exposures. */
  async function submitSampleScan() {
    const error = $("upload-error");
    const button = $("sample-scan-button");
    error.hidden = true;
    button.disabled = true;
    try {
      const blob = await (await api("/samples/room_scan.mp4")).blob();
      await submitJob(new File([blob], "room_scan.mp4", { type: "video/mp4" }), null, {});
    } catch (e) {
      error.textContent = e instanceof ApiError ? e.message : `Sample failed: ${e.message}`;
      error.hidden = false;
    } finally {
      button.disabled = false;
    }
  }

  async function submitJob(file, depth, params) {
    const form = new FormData();
    form.append("file", file, file.name);
    if (depth) form.append("depth", depth, depth.name);
    form.append("params", JSON.stringify(params));
    const created = await apiJson("/jobs", { method: "POST", body: form });
    uploads.set(created.id, { file, depth });
    closeResult();
    showPending(file);
    refreshJobs();
    watchJob(created.id).catch(reportError);
    return created;
  }

  /** Re-estimate the open job with a corrected horizontal FOV: the same file and params, new
   * intrinsics. Without the file in this tab, the upload form is filled in instead. */
  async function correctFov(event) {
    event.preventDefault();
    const hfov = parseFloat($("fov-correct").value);
    const status = $("fov-status");
    if (!(hfov > 0 && hfov < 180) || !view.id) { status.textContent = "Give a FOV between 0 and 180°."; return; }
    let params = {};
    try {
      params = (await apiJson(`/jobs/${view.id}`)).params || {};
    } catch (error) { reportError(error); return; }
    const corrected = { ...params, intrinsics: { hfov_deg: hfov } };
    const upload = uploads.get(view.id);
    if (!upload) {
      $("hfov-input").value = String(hfov);
      if (corrected.preset) $("preset-input").value = corrected.preset;
      if (corrected.temporal) $("temporal-input").value = corrected.temporal;
      if (corrected.fps) $("fps-input").value = String(corrected.fps);
      status.textContent = `Choose the same file under “New estimate” to re-estimate with ${hfov}°.`;
      $("file-input").focus();
      return;
    }
    $("fov-button").disabled = true;
    status.textContent = "Uploading…";
    try {
      await submitJob(upload.file, upload.depth, corrected);
    } catch (error) {
      status.textContent = error instanceof ApiError ? error.message : `Upload failed: ${error.message}`;
    } finally {
      $("fov-button").disabled = false;
    }
  }

  /** The camera the estimate used: FOV and where it came from, depth source, tracking. */
  function showCamera(capture) {
    const k = capture.intrinsics;
    const hfov = (2 * Math.atan(0.5 * k.width / k.fx) * 180) / Math.PI;
    $("fov-value").textContent = `${hfov.toFixed(1)}°`;
    $("fov-source").textContent = capture.intrinsics_source ? `(${capture.intrinsics_source})` : "";
    $("fov-correct").value = hfov.toFixed(1);
    $("fov-status").textContent = "";
    $("depth-source").textContent = capture.depth_source;
    const t = capture.tracking || null;
    let camera = capture.static_camera === false ? "moves (poses given)" : "static";
    if (t && t.method) {
      const err = t.reprojection_error_px == null ? "" : `, reprojection error ${Number(t.reprojection_error_px).toFixed(2)} px`;
      const dropped = (t.frames_dropped || []).length ? `, ${t.frames_dropped.length} frame(s) dropped` : "";
      camera = {
        static: "static (no camera motion found)",
        rotation: `tracked: turns about a fixed point${err}${dropped}`,
        "sfm:pycolmap": `tracked: structure from motion (COLMAP)${err}${dropped}, scale: ${t.scale_source}`,
        "sfm:opencv": `tracked: structure from motion (OpenCV)${err}${dropped}, scale: ${t.scale_source}`,
        "failed:static-fallback": "tracking FAILED: treated as static (give poses for a moving camera)",
        off: "static (tracking turned off)",
      }[t.method] || t.method;
    } else if (capture.poses_source) {
      camera = `${capture.static_camera ? "static" : "moves"} (${capture.poses_source})`;
    }
    $("camera-source").textContent = camera;
    const ev = capture.frame_ev || null;
    const span = ev && ev.length ? ` (${(Math.max(...ev) - Math.min(...ev)).toFixed(2)} stops over the clip)` : "";
    $("exposure-source").textContent = capture.exposure_source ? `${capture.exposure_source}${span}` : "locked (one exposure for every frame)";
    $("camera-source").classList.toggle("warning", Boolean(t && t.method === "failed:static-fallback"));
    showGrade(capture.grade || {});
    const notes = capture.notes || [];
    $("capture-notes").hidden = !notes.length;
    $("capture-notes").textContent = notes.length ? `From the file: ${notes.join("; ")}` : "";
  }

  /** The job's self-check: its grade, the share of the sphere seen vs filled, a fallback in words. */
  function showGrade(g) {
    const pct = (v) => `${Math.round(100 * v)} %`;
    const shares = g.seen_share == null ? "" : ` · seen ${pct(g.seen_share)}, filled ${pct(g.filled_share)}`;
    const fallback = g.fallback ? ` · answered with the capture's constant map: ${g.fallback}` : "";
    $("grade-info").textContent = `${g.grade || "unchecked"}${shares}${fallback}`;
    $("grade-info").classList.toggle("warning", Boolean(g.fallback) || g.grade === "worse than a constant map");
  }

  // ------------------------------------------------------------------ jobs list
  async function refreshJobs() {
    let list;
    try {
      list = await apiJson("/jobs?limit=20");
    } catch (error) {
      if (!(error instanceof ApiError && error.status === 401)) reportError(error);
      return;
    }
    const ul = $("jobs-list");
    ul.replaceChildren();
    if (!list.jobs.length) {
      ul.innerHTML = '<li class="muted small">No jobs yet.</li>';
      return;
    }
    for (const j of list.jobs) {
      const li = document.createElement("li");
      const b = document.createElement("button");
      b.type = "button";
      b.dataset.jobId = j.id;
      b.innerHTML = '<span class="job-id"></span><span class="job-state"></span><span class="job-when"></span>';
      b.querySelector(".job-id").textContent = `${j.id.slice(0, 8)} · ${j.input_kind}`;
      b.querySelector(".job-state").textContent = j.state;
      b.querySelector(".job-state").dataset.state = j.state;
      b.querySelector(".job-when").textContent = `${fmt.when(j.created_at)} · ${j.params.preset || ""}`;
      b.addEventListener("click", () => openJob(j.id).catch(reportError));
      li.append(b);
      ul.append(li);
    }
    markCurrentJob();
  }

  function markCurrentJob() {
    for (const b of document.querySelectorAll("#jobs-list button")) {
      b.classList.toggle("current", b.dataset.jobId === job.id);
    }
  }

  async function openJob(id) {
    closeResult();
    await watchJob(id);
    if (view.id === id) {
      try {
        const info = await apiJson(`/lightfield/${id}`);
        const curve = (info.metadata.training || {}).loss_curve || [];
        const total = (info.metadata.training || {}).iterations || curve.length;
        if (lossChart.points.length < 2 && curve.length > 1) {
          lossChart.reset(curve.map((l, i) => [Math.round((i * total) / (curve.length - 1)), l]));
        }
      } catch (error) { reportError(error); }
    }
  }

  // ------------------------------------------------------------------ result view
  const view = {
    id: null,
    capture: null,
    frameIndex: 0,
    probes: [],
    selected: null,
    nextNumber: 1,
    ev: 0,
    autoExposed: false,
  };
  const frameSlot = latestOnly();
  const envmapSlot = latestOnly();

  const frameTime = () => view.capture.times[view.frameIndex];
  const selectedProbe = () => view.probes.find((p) => p.number === view.selected) || null;

  function closeResult() {
    Object.assign(view, { id: null, capture: null, probes: [], selected: null, nextNumber: 1, autoExposed: false });
    $("result").hidden = true;
    $("no-frames").hidden = true;
    $("empty-state").hidden = false;
    showPending(null);
    stopPlaying();
  }

  async function openResult(id) {
    history.replaceState(null, "", `#job=${id}`);
    let capture;
    $("empty-state").hidden = true;
    $("loading").hidden = false;
    try {
      capture = await apiJson(`/lightfield/${id}/capture`);
    } catch (error) {
      $("loading").hidden = true;
      $("empty-state").hidden = false;
      if (error instanceof ApiError && error.code === "frames_unavailable") {
        $("empty-state").hidden = true;
        $("no-frames").hidden = false;
        return;
      }
      throw error;
    }
    $("loading").hidden = true;
    showPending(null);
    Object.assign(view, { id, capture, frameIndex: 0, probes: [], selected: null, nextNumber: 1, autoExposed: false });
    const slider = $("time-slider");
    slider.max = String(capture.frames - 1);
    slider.value = "0";
    $("time-row").hidden = capture.frames < 2; // a single image has no time to scrub
    $("time-label").textContent = fmt.time(capture.times[0]);
    $("capture-info").textContent = [
      `${capture.width}×${capture.height} preview`,
      `${capture.frames} frame${capture.frames === 1 ? "" : "s"}${capture.frames > 1 ? ` at ${capture.fps.toPrecision(3)} fps` : ""}`,
      capture.uses_time ? "lighting varies over time" : "lighting constant over time",
    ].join(" · ");
    showCamera(capture);
    $("empty-state").hidden = true;
    $("result").hidden = false;
    renderProbes();
    await refreshFrame();
  }

  /** The probes in view at this frame, as /insertion's points "u,v,depth;...". */
  function framePoints() {
    return view.probes
      .filter((p) => p.placement.visible)
      .map(({ placement: pl }) => `${pl.u.toFixed(5)},${pl.v.toFixed(5)},${pl.depth.toPrecision(6)}`)
      .join(";");
  }

  async function refreshFrame() {
    if (!view.capture) return;
    const t = frameTime();
    const withBalls = $("balls-toggle").checked && framePoints() !== "";
    const path = withBalls
      ? `/lightfield/${view.id}/insertion?${query({ t, points: framePoints() })}`
      : `/lightfield/${view.id}/frame?${query({ t })}`;
    const key = `${view.frameIndex}|${withBalls ? framePoints() : "plain"}`;
    const img = $("frame-img");
    $("frame-label").textContent = `${view.frameIndex + 1} / ${view.capture.frames}`;
    $("viewer-busy").hidden = false;
    try {
      if (withBalls && !(img.dataset.key || "").startsWith(`${view.frameIndex}|`)) {
        // a new frame: show it at once, the balls follow when rendered (they take a moment)
        const plain = await frameSlot(async () => (await api(`/lightfield/${view.id}/frame?${query({ t })}`)).blob());
        await showBlob(img, plain, `${view.frameIndex}|plain`);
        fitFrame();
      }
      const blob = await frameSlot(async () => (await api(path)).blob());
      await showBlob(img, blob, key);
      fitFrame();
      $("viewer-busy").hidden = true;
    } catch (error) {
      if (error !== STALE) $("viewer-busy").hidden = true;
      throw error;
    }
  }

  /** As large as the card allows, but no taller than 72 % of the window (portrait videos). */
  function fitFrame() {
    const img = $("frame-img");
    if (!img.naturalWidth) return;
    const box = img.closest(".viewer").clientWidth;
    if (!box) return;
    const aspect = img.naturalWidth / img.naturalHeight;
    $("viewer").style.width = `${Math.min(box, 0.72 * window.innerHeight * aspect)}px`;
  }

  // ------------------------------------------------------------------ probes
  // A probe is a point fixed in the world: created on a pixel's ray, then followed from frame
  // to frame by its world position x (with a moving camera it moves on screen, not in the room).
  async function placeOnPixel(probe, u, v, depth = null) {
    const params = { u, v, t: frameTime() };
    if (depth != null) params.depth = depth;
    probe.placement = await apiJson(`/lightfield/${view.id}/probe?${query(params)}`);
  }

  async function followProbe(probe) {
    const params = { x: probe.placement.x.join(","), t: frameTime() };
    probe.placement = await apiJson(`/lightfield/${view.id}/probe?${query(params)}`);
  }

  async function addProbe(u, v) {
    const probe = { number: view.nextNumber++, placement: null };
    await placeOnPixel(probe, u, v);
    view.probes.push(probe);
    view.selected = probe.number;
    renderProbes();
    await Promise.all([refreshFrame(), refreshEnvmap({ autoExpose: !view.autoExposed })]);
  }

  function removeProbe(number) {
    view.probes = view.probes.filter((p) => p.number !== number);
    if (view.selected === number) view.selected = view.probes.length ? view.probes[view.probes.length - 1].number : null;
    renderProbes();
    refreshFrame().catch(reportError);
    if (view.selected != null) refreshEnvmap().catch(reportError);
  }

  function selectProbe(number) {
    view.selected = number;
    renderProbes();
    refreshEnvmap().catch(reportError);
  }

  function renderProbes() {
    const list = $("probe-list");
    const markers = $("probe-markers");
    list.replaceChildren();
    markers.replaceChildren();
    $("probe-count").textContent = view.probes.length ? `${view.probes.length} placed` : "none yet";
    if (!view.probes.length) {
      list.innerHTML = '<li class="probe-empty muted small">Click anywhere in the frame to place a light probe there.</li>';
    }
    for (const p of view.probes) {
      const selected = p.number === view.selected;
      const li = document.createElement("li");
      li.className = selected ? "selected" : "";
      li.dataset.probe = String(p.number);
      li.dataset.u = String(p.placement.u);
      li.dataset.v = String(p.placement.v);
      li.innerHTML = '<span class="probe-index"></span><span class="probe-text"></span><button type="button" class="remove" aria-label="remove probe">×</button>';
      li.querySelector(".probe-index").textContent = String(p.number);
      li.querySelector(".probe-text").textContent = `x ${fmt.vec(p.placement.x)} · ` +
        (p.placement.visible ? fmt.metres(p.placement.depth) : "not in this frame");
      li.addEventListener("click", () => selectProbe(p.number));
      li.querySelector(".remove").addEventListener("click", (e) => { e.stopPropagation(); removeProbe(p.number); });
      list.append(li);
      if (!p.placement.visible) continue;

      const m = document.createElement("div");
      m.className = `marker${selected ? " selected" : ""}`;
      m.style.left = `${100 * p.placement.u}%`;
      m.style.top = `${100 * p.placement.v}%`;
      m.append(Object.assign(document.createElement("span"), { textContent: String(p.number) }));
      m.title = `probe ${p.number}`;
      m.addEventListener("click", (e) => { e.stopPropagation(); selectProbe(p.number); });
      markers.append(m);
    }
    renderProbeDetail();
  }

  // The depth slider spans (0, 1.6 x the surface depth] on a square-root scale, which gives
  // more travel close to the camera where a small change moves the probe a lot on screen.
  function depthRange(p) {
    return 1.6 * (p.placement.surface_depth ?? p.placement.default_depth);
  }
  const sliderToDepth = (p, s) => depthRange(p) * Math.max((s / 1000) ** 2, 1e-4);
  const depthToSlider = (p, d) => Math.round(1000 * Math.sqrt(Math.min(d / depthRange(p), 1)));

  function renderProbeDetail() {
    const p = selectedProbe();
    $("probe-detail").hidden = !p;
    if (!p) return;
    const pl = p.placement;
    $("depth-slider").disabled = $("depth-reset").disabled = !pl.visible;
    $("depth-slider").value = String(pl.visible ? depthToSlider(p, pl.depth) : 0);
    $("depth-label").textContent = pl.visible ? fmt.metres(pl.depth) : "—";
    $("probe-position").textContent =
      `probe ${p.number} · x = (${fmt.vec(pl.x)}) m · surface ${fmt.metres(pl.surface_depth)} · ball radius ${fmt.metres(pl.radius)}`;
    let warn = [];
    if (pl.extrapolated.x) warn.push("outside the region the capture saw");
    if (pl.extrapolated.t) warn.push("outside the captured time range");
    if (warn.length) warn = [`Extrapolated: ${warn.join("; ")}.`];
    if (!pl.visible) warn.push("Not in view in this frame (behind or beside the camera); its light is still shown.");
    else if (pl.surface_depth == null) warn.push("No depth at this pixel: the default depth is a guess.");
    $("probe-warning").hidden = !warn.length;
    $("probe-warning").textContent = warn.join(" ");
  }

  /** Move the selected probe along its pixel's ray in this frame (null: the default depth). */
  async function setProbeDepth(depth) {
    const p = selectedProbe();
    if (!p || !p.placement.visible) return;
    await placeOnPixel(p, p.placement.u, p.placement.v, depth);
    renderProbes();
    await Promise.all([refreshFrame(), refreshEnvmap()]);
  }

  // ------------------------------------------------------------------ env map + exposure
  function envmapQuery(p, extra) {
    return query({ x: p.placement.x.join(","), t: frameTime(), ...extra });
  }

  async function refreshEnvmap({ autoExpose = false } = {}) {
    const p = selectedProbe();
    if (!p) return;
    if (autoExpose) {
      await autoExposure(p);
      view.autoExposed = true;
    }
    const q = envmapQuery(p, { format: "png", height: ENVMAP_VIEW_HEIGHT, ev: view.ev });
    const key = `${p.number}|${view.frameIndex}|${p.placement.x.join(",")}|${view.ev}`;
    const blob = await envmapSlot(async () => (await api(`/lightfield/${view.id}/envmap?${q}`)).blob());
    await showBlob($("envmap-img"), blob, key);
  }

  /** Float32 array and shape of a little-endian .npy (what the API's format=npy returns). */
  function parseNpy(buffer) {
    const bytes = new Uint8Array(buffer);
    const major = bytes[6];
    const view32 = new DataView(buffer);
    const headerLen = major === 1 ? view32.getUint16(8, true) : view32.getUint32(8, true);
    const offset = (major === 1 ? 10 : 12) + headerLen;
    const header = new TextDecoder().decode(bytes.subarray(offset - headerLen, offset));
    if (!header.includes("'<f4'")) throw new Error("expected a float32 .npy");
    const shape = (header.match(/'shape':\s*\(([^)]*)\)/) || [, ""])[1].split(",").filter((s) => s.trim()).map(Number);
    return { data: new Float32Array(buffer.slice(offset)), shape };
  }

  /** Exposure that maps the map's 99th-percentile luminance to a display value of 0.85. */
  async function autoExposure(p) {
    const q = envmapQuery(p, { format: "npy", height: AUTO_EXPOSURE_HEIGHT });
    const { data } = parseNpy(await (await api(`/lightfield/${view.id}/envmap?${q}`)).arrayBuffer());
    const lum = [];
    for (let i = 0; i + 2 < data.length; i += 3) {
      const y = 0.2127 * data[i] + 0.7152 * data[i + 1] + 0.0722 * data[i + 2];
      if (isFinite(y)) lum.push(y);
    }
    lum.sort((a, b) => a - b);
    const level = lum[Math.min(lum.length - 1, Math.floor(AUTO_EXPOSURE_PERCENTILE * lum.length))] || 0;
    if (level > 0) setExposure(Math.log2(AUTO_EXPOSURE_TARGET ** GAMMA / level));
  }

  function setExposure(ev) {
    const clamped = Math.min(EV_RANGE[1], Math.max(EV_RANGE[0], Math.round(ev * 4) / 4));
    view.ev = clamped;
    $("exposure-slider").value = String(clamped);
    $("exposure-label").textContent = `${clamped >= 0 ? "+" : ""}${clamped.toFixed(2)} EV`;
  }

  // ------------------------------------------------------------------ time
  let timeTimer = null;
  async function setFrame(index) {
    view.frameIndex = index;
    $("time-slider").value = String(index);
    $("time-label").textContent = fmt.time(frameTime());
    await Promise.all(view.probes.map(followProbe));
    renderProbes();
    await Promise.all([refreshFrame(), refreshEnvmap()]);
  }

  function onTimeInput() {
    const index = Number($("time-slider").value);
    $("time-label").textContent = fmt.time(view.capture.times[index]);
    clearTimeout(timeTimer);
    timeTimer = setTimeout(() => setFrame(index).catch(reportError), 120);
  }

  let playing = false;
  function stopPlaying() {
    playing = false;
    $("play-button").textContent = "▶";
  }
  async function togglePlay() {
    if (playing) return stopPlaying();
    playing = true;
    $("play-button").textContent = "❚❚";
    while (playing && view.capture) {
      const next = (view.frameIndex + 1) % view.capture.frames;
      try { await setFrame(next); } catch (error) { if (error !== STALE) { reportError(error); break; } }
      await new Promise((r) => setTimeout(r, 200));
    }
    stopPlaying();
  }

  // ------------------------------------------------------------------ downloads
  function saveBlob(blob, name) {
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = name;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 30000);
  }

  async function download(kind) {
    const p = selectedProbe();
    if (!p) return;
    const stem = `lightfield_${view.id.slice(0, 8)}_p${p.number}_t${frameTime().toFixed(3)}`;
    const base = `/lightfield/${view.id}`;
    const requests = {
      exr: [`${base}/envmap?${envmapQuery(p, { format: "exr", height: ENVMAP_DOWNLOAD_HEIGHT })}`, `${stem}.exr`],
      hdr: [`${base}/envmap?${envmapQuery(p, { format: "hdr", height: ENVMAP_DOWNLOAD_HEIGHT })}`, `${stem}.hdr`],
      sh: [`${base}/sh?${envmapQuery(p, {})}`, `${stem}_sh.json`],
      cubemap: [`${base}/cubemap?${envmapQuery(p, { size: CUBEMAP_DOWNLOAD_SIZE, format: "json" })}`, `${stem}_cubemap.json`],
    };
    const [path, name] = requests[kind];
    const status = $("download-status");
    status.textContent = `Preparing ${name}…`;
    try {
      saveBlob(await (await api(path)).blob(), name);
      status.textContent = `Saved ${name}`;
    } catch (error) {
      status.textContent = "";
      reportError(error);
    }
  }

  // ------------------------------------------------------------------ wiring
  /** The job named in the address (…/ui/#job=ID), so a link or a reload reopens it. */
  const linkedJob = () => new URLSearchParams(location.hash.slice(1)).get("job");

  function onFrameClick(event) {
    if (!view.capture) return;
    const rect = $("frame-img").getBoundingClientRect();
    const u = Math.min(1, Math.max(0, (event.clientX - rect.left) / rect.width));
    const v = Math.min(1, Math.max(0, (event.clientY - rect.top) / rect.height));
    addProbe(u, v).catch(reportError);
  }

  function init() {
    $("api-key").value = auth.key;
    $("key-form").addEventListener("submit", useKey);
    $("upload-form").addEventListener("submit", submitUpload);
    $("sample-scan-button").addEventListener("click", submitSampleScan);
    $("fov-form").addEventListener("submit", (e) => correctFov(e).catch(reportError));
    $("cancel-button").addEventListener("click", cancelJob);
    $("jobs-refresh").addEventListener("click", refreshJobs);
    $("viewer").addEventListener("click", onFrameClick);
    $("balls-toggle").addEventListener("change", () => refreshFrame().catch(reportError));
    $("time-slider").addEventListener("input", onTimeInput);
    $("play-button").addEventListener("click", togglePlay);
    $("depth-slider").addEventListener("input", () => {
      const p = selectedProbe();
      if (p) $("depth-label").textContent = fmt.metres(sliderToDepth(p, Number($("depth-slider").value)));
    });
    $("depth-slider").addEventListener("change", () => {
      const p = selectedProbe();
      if (p) setProbeDepth(sliderToDepth(p, Number($("depth-slider").value))).catch(reportError);
    });
    $("depth-reset").addEventListener("click", () => setProbeDepth(null).catch(reportError));
    $("exposure-slider").addEventListener("input", () => setExposure(Number($("exposure-slider").value)));
    $("exposure-slider").addEventListener("change", () => refreshEnvmap().catch(reportError));
    $("exposure-auto").addEventListener("click", () => refreshEnvmap({ autoExpose: true }).catch(reportError));
    for (const b of document.querySelectorAll("[data-download]")) {
      b.addEventListener("click", () => download(b.dataset.download));
    }
    window.addEventListener("resize", () => { lossChart.draw(); fitFrame(); });
    setExposure(0);
    lossChart.draw();
    refreshJobs();
    window.addEventListener("hashchange", () => {
      if (linkedJob() && linkedJob() !== view.id) openJob(linkedJob()).catch(reportError);
    });
    if (linkedJob()) openJob(linkedJob()).catch(reportError);
  }

  init();
})();
