// sprint-map viewer: plain JavaScript and canvas, no library, no network beyond this server.
// The server summarises the map (sprint_map/viewer/overview.py); this page only draws.
"use strict";
(function () {
  const API = "/viewer/api";
  const $ = (id) => document.getElementById(id);
  const V = (window.sprintViewer = { drawn: [], errors: [], ready: false });

  // --- talking to the server (bearer token when the server has one) ------------------------
  let token = sessionStorage.getItem("sprint-map-token") || "";
  let pendingLogin = null;
  async function api(path) {
    for (;;) {
      const headers = token ? { Authorization: "Bearer " + token } : {};
      const res = await fetch(API + path, { headers });
      if (res.status === 401) { await askToken(); continue; }
      if (!res.ok) {
        let msg = res.status + " " + res.statusText;
        try { msg = (await res.json()).message || msg; } catch (e) { /* not JSON */ }
        throw new Error(msg);
      }
      return (res.headers.get("content-type") || "").includes("json") ? res.json() : res.blob();
    }
  }
  function askToken() {
    if (!pendingLogin) {
      pendingLogin = new Promise((resolve) => {
        const form = $("login");
        form.hidden = false;
        form.onsubmit = (ev) => {
          ev.preventDefault();
          token = $("token").value.trim();
          sessionStorage.setItem("sprint-map-token", token);
          form.hidden = true;
          pendingLogin = null;
          resolve();
        };
      });
    }
    return pendingLogin;
  }
  function fail(err) {
    const box = $("error");
    box.hidden = false;
    box.textContent = "Error: " + (err && err.message ? err.message : err);
  }

  // --- colours: one per component ------------------------------------------------------------
  function hslToRgb(h, s, l) {
    const k = (n) => (n + h * 12) % 12;
    const a = s * Math.min(l, 1 - l);
    const f = (n) => l - a * Math.max(-1, Math.min(k(n) - 3, Math.min(9 - k(n), 1)));
    return [Math.round(255 * f(0)), Math.round(255 * f(8)), Math.round(255 * f(4))];
  }
  const compColour = new Map();
  function colourOfComponent(c) {
    if (!compColour.has(c)) {
      const i = compColour.size;
      compColour.set(c, hslToRgb((i * 0.618034) % 1, 0.7, 0.42));
    }
    return compColour.get(c);
  }
  const css = (rgb, a) => (a === undefined ? `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`
    : `rgba(${rgb[0]},${rgb[1]},${rgb[2]},${a})`);
  const fmtBytes = (n) => (n > 1 << 30 ? (n / (1 << 30)).toFixed(2) + " GiB"
    : n > 1 << 20 ? (n / (1 << 20)).toFixed(1) + " MiB" : (n / 1024).toFixed(0) + " KiB");
  const el = (tag, attrs, ...kids) => {
    const e = document.createElement(tag);
    Object.assign(e, attrs || {});
    for (const k of kids) e.append(k);
    return e;
  };

  // --- tabs ------------------------------------------------------------------------------------
  function showTab(name) {
    for (const b of document.querySelectorAll("nav .tab")) b.classList.toggle("active", b.dataset.tab === name);
    for (const p of document.querySelectorAll(".panel")) p.hidden = p.id !== name;
    if (name === "overview") drawOverview();
    if (name === "trace") drawTrace();
  }
  for (const b of document.querySelectorAll("nav .tab")) b.onclick = () => showTab(b.dataset.tab);

  // --- overview ----------------------------------------------------------------------------------
  let ov = null; // the overview JSON
  const view = { scale: 1, ox: 0, oy: 0 }; // grid -> CSS pixels: x * scale + ox, oy - y * scale
  const seqIndex = new Map();
  function fitCanvas(canvas) {
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    return [ctx, w, h];
  }
  let extent = [0, 0, 1, 1]; // grid units: what is drawn (set when the overview loads)
  function resetView() {
    const c = $("overview-canvas");
    const w = c.clientWidth, h = c.clientHeight;
    const ew = Math.max(extent[2] - extent[0], 1), eh = Math.max(extent[3] - extent[1], 1);
    view.scale = 0.92 * Math.min(w / ew, h / eh);
    view.ox = (w - ew * view.scale) / 2 - extent[0] * view.scale;
    view.oy = h - (h - eh * view.scale) / 2 + extent[1] * view.scale;
  }
  function computeExtent() {
    const pts = ov.mode === "positions" ? ov.xy : ov.layout;
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (let i = 0; i + 1 < pts.length; i += 2) {
      x0 = Math.min(x0, pts[i]); x1 = Math.max(x1, pts[i]);
      y0 = Math.min(y0, pts[i + 1]); y1 = Math.max(y1, pts[i + 1]);
    }
    extent = pts.length ? [x0, y0, x1, y1] : [0, 0, ov.grid, ov.grid];
  }
  const sx = (x) => x * view.scale + view.ox;
  const sy = (y) => view.oy - y * view.scale;
  // Where each drive starts in ov.xy (positions mode), by index in ov.sequences.
  let pointStart = [];

  function drawOverview() {
    if (!ov) return;
    const canvas = $("overview-canvas");
    const [ctx, w, h] = fitCanvas(canvas);
    ctx.clearRect(0, 0, w, h);
    const seqs = ov.sequences;
    const drawn = [];
    ctx.lineCap = "round"; ctx.lineJoin = "round";
    if (ov.mode === "positions") {
      const xy = ov.edges.xy;
      ctx.strokeStyle = "rgba(120,120,120,0.35)"; ctx.lineWidth = 1;
      ctx.beginPath();
      for (let i = 0; i + 3 < xy.length; i += 4) {
        ctx.moveTo(sx(xy[i]), sy(xy[i + 1])); ctx.lineTo(sx(xy[i + 2]), sy(xy[i + 3]));
      }
      ctx.stroke();
      ctx.lineWidth = 2.5;
      for (let s = 0; s < seqs.id.length; s++) {
        const n = ov.points[s];
        if (!n) continue;
        const p = ov.xy, o = pointStart[s];
        ctx.strokeStyle = css(colourOfComponent(seqs.component[s]));
        ctx.beginPath();
        ctx.moveTo(sx(p[o]), sy(p[o + 1]));
        for (let k = 1; k < n; k++) ctx.lineTo(sx(p[o + 2 * k]), sy(p[o + 2 * k + 1]));
        if (n === 1) ctx.lineTo(sx(p[o]) + 0.1, sy(p[o + 1]));
        ctx.stroke();
        drawn.push(seqs.id[s]);
      }
    } else {
      const L = ov.layout, pairs = ov.pairs;
      ctx.strokeStyle = "rgba(120,120,120,0.5)";
      for (let i = 0; i < pairs.a.length; i++) {
        const a = seqIndex.get(pairs.a[i]), b = seqIndex.get(pairs.b[i]);
        ctx.lineWidth = Math.min(6, 0.5 + Math.log10(1 + pairs.edges[i]));
        ctx.beginPath();
        ctx.moveTo(sx(L[2 * a]), sy(L[2 * a + 1])); ctx.lineTo(sx(L[2 * b]), sy(L[2 * b + 1]));
        ctx.stroke();
      }
      const maxFrames = Math.max(1, ...seqs.frames);
      for (let s = 0; s < seqs.id.length; s++) {
        const r = 3 + 7 * Math.sqrt(seqs.frames[s] / maxFrames);
        ctx.fillStyle = css(colourOfComponent(seqs.component[s]));
        ctx.beginPath(); ctx.arc(sx(L[2 * s]), sy(L[2 * s + 1]), r, 0, 2 * Math.PI); ctx.fill();
        drawn.push(seqs.id[s]);
      }
    }
    V.drawn = drawn;
    $("overview-legend").textContent = ov.mode === "positions"
      ? `drives on their positions; edges ${ov.edges.level === "vertex" ? "one by one" : "sampled per pair of drives"} (${ov.edges.drawn} drawn of ${ov.counts.edges}); wheel: zoom, drag: pan, click: open a drive`
      : `no positions: layout of the sequence graph (node: drive, line: edges between two drives); click a node`;
  }

  // Canvas CSS-pixel point on a drive's drawing (tests and hit-testing use it).
  V.screenOf = function (seqId) {
    const s = seqIndex.get(seqId);
    if (s === undefined || !ov) return null;
    if (ov.mode === "positions") {
      const n = ov.points[s];
      if (!n) return null;
      const o = pointStart[s] + 2 * Math.floor(n / 2);
      return [sx(ov.xy[o]), sy(ov.xy[o + 1])];
    }
    return [sx(ov.layout[2 * s]), sy(ov.layout[2 * s + 1])];
  };
  V.colourOf = (seqId) => colourOfComponent(ov.sequences.component[seqIndex.get(seqId)]);

  function nearestDrive(px, py) {
    let best = null, bestD = 12 * 12;
    const seqs = ov.sequences;
    for (let s = 0; s < seqs.id.length; s++) {
      if (ov.mode === "positions") {
        const o = pointStart[s];
        for (let k = 0; k < ov.points[s]; k++) {
          const dx = sx(ov.xy[o + 2 * k]) - px, dy = sy(ov.xy[o + 2 * k + 1]) - py;
          if (dx * dx + dy * dy < bestD) { bestD = dx * dx + dy * dy; best = seqs.id[s]; }
        }
      } else {
        const dx = sx(ov.layout[2 * s]) - px, dy = sy(ov.layout[2 * s + 1]) - py;
        if (dx * dx + dy * dy < bestD) { bestD = dx * dx + dy * dy; best = seqs.id[s]; }
      }
    }
    return best;
  }

  function setupOverviewEvents() {
    const c = $("overview-canvas");
    let drag = null, moved = false;
    c.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      const f = Math.exp(-ev.deltaY * 0.0015);
      const r = c.getBoundingClientRect(), mx = ev.clientX - r.left, my = ev.clientY - r.top;
      view.ox = mx - (mx - view.ox) * f; view.oy = my - (my - view.oy) * f; view.scale *= f;
      drawOverview();
    }, { passive: false });
    c.addEventListener("mousedown", (ev) => { drag = [ev.clientX, ev.clientY]; moved = false; });
    window.addEventListener("mousemove", (ev) => {
      if (!drag) return;
      const dx = ev.clientX - drag[0], dy = ev.clientY - drag[1];
      if (Math.abs(dx) + Math.abs(dy) > 2) moved = true;
      view.ox += dx; view.oy += dy; drag = [ev.clientX, ev.clientY];
      if (moved) drawOverview();
    });
    window.addEventListener("mouseup", (ev) => {
      if (drag && !moved && ev.target === c) {
        const r = c.getBoundingClientRect();
        const id = nearestDrive(ev.clientX - r.left, ev.clientY - r.top);
        if (id !== null) openDrive(id);
      }
      drag = null;
    });
    c.addEventListener("dblclick", () => { resetView(); drawOverview(); });
    window.addEventListener("resize", () => { if (ov) { resetView(); drawOverview(); } });
  }

  function fillDriveList() {
    const body = $("drive-list").tBodies[0];
    body.textContent = "";
    const seqs = ov.sequences;
    for (let s = 0; s < seqs.id.length; s++) {
      const tr = el("tr", { id: "drive-row-" + seqs.id[s] },
        el("td", {}, el("span", { className: "swatch", style: `background:${css(colourOfComponent(seqs.component[s]))}` })),
        el("td", { textContent: seqs.name[s] + (seqs.positions[s] || ov.mode === "layout" ? "" : " (no positions)") }),
        el("td", { textContent: seqs.frames[s] }), el("td", { textContent: seqs.component[s] }));
      tr.onclick = () => openDrive(seqs.id[s]);
      body.append(tr);
    }
  }

  async function loadOverview() {
    ov = await api("/overview");
    const seqs = ov.sequences;
    seqIndex.clear();
    seqs.id.forEach((id, i) => seqIndex.set(id, i));
    for (const c of [...new Set(seqs.component)].sort((a, b) => a - b)) colourOfComponent(c);
    pointStart = [];
    let o = 0;
    for (let s = 0; s < seqs.id.length; s++) { pointStart.push(o); o += 2 * (ov.points ? ov.points[s] : 0); }
    $("map-path").textContent = ov.path;
    const c = ov.counts;
    $("counts").textContent = `${c.sequences} drives · ${c.vertices} vertices · ${c.edges} edges · ` +
      `${c.components} components · ${fmtBytes(c.disk_bytes)} on disk`;
    computeExtent();
    resetView();
    drawOverview();
    performance.mark("overview-drawn");
    V.overviewDrawnAt = performance.now();
    fillDriveList();
  }

  // --- a drive: matched drives, the similarity matrix with its decisions --------------------
  let drive = null, matrix = null;
  async function openDrive(seqId) {
    const tab = document.querySelector('nav .tab[data-tab="drive"]');
    tab.disabled = false;
    showTab("drive");
    drive = await api("/sequences/" + seqId);
    $("drive-title").textContent = `Drive ${drive.name} (sequence ${drive.seq_id})`;
    $("drive-info").textContent = `${drive.frames} frames · component ${drive.component} · ` +
      `${drive.edges} edges to ${drive.matched.length} drives` +
      (drive.precision !== null ? ` · precision of its edges ${(100 * drive.precision).toFixed(1)} %` : "") +
      (drive.thumbnails ? ` · ${drive.thumbnails} thumbnails` : "");
    const box = $("matched");
    box.textContent = "";
    if (!drive.matched.length) box.textContent = "This drive shares no edge with another drive.";
    for (const m of drive.matched) {
      const b = el("button", { textContent: `${m.name} (${m.edges} edges)` });
      b.dataset.other = m.seq_id;
      b.onclick = () => openMatrix(m.seq_id);
      box.append(b);
    }
    $("thumbs").hidden = !drive.thumbnails;
    const ctx = $("matrix-canvas").getContext("2d");
    ctx.clearRect(0, 0, 520, 520);
    $("matrix-info").textContent = ""; $("pr").textContent = "";
    if (drive.matched.length) await openMatrix(drive.matched[0].seq_id);
    V.driveShown = seqId;
  }

  async function openMatrix(other) {
    for (const b of $("matched").children) b.classList.toggle("active", Number(b.dataset.other) === other);
    matrix = await api(`/matrix/${drive.seq_id}/${other}`);
    drawMatrix();
    const m = matrix, names = new Map(drive.matched.map((x) => [x.seq_id, x.name]));
    $("matrix-info").textContent = `rows: ${drive.name} (${m.frames[0]} frames, ${m.rows.length} sampled) · ` +
      `columns: ${names.get(other)} (${m.frames[1]} frames, ${m.cols.length} sampled) · ` +
      `${m.decisions.frame.length} decisions · brighter = more similar descriptors`;
    $("pr").textContent = m.pr
      ? `Ground truth from positions (within ${m.pr.radius_m} m): precision ${fmtPct(m.pr.precision)}` +
        ` (${m.pr.correct}/${m.pr.decisions}), recall ${fmtPct(m.pr.recall)} of ${m.pr.frames_with_match} frames with a true match`
      : "No ground truth (one of the drives has no positions).";
    V.matrixShown = other;
  }
  const fmtPct = (x) => (x === null ? "n/a" : (100 * x).toFixed(1) + " %");

  function drawMatrix() {
    const m = matrix, canvas = $("matrix-canvas"), ctx = canvas.getContext("2d");
    const rows = m.rows.length, cols = m.cols.length;
    const raw = atob(m.pixels);
    const img = ctx.createImageData(cols, rows);
    for (let i = 0; i < rows * cols; i++) {
      const v = raw.charCodeAt(i);
      img.data[4 * i] = v; img.data[4 * i + 1] = v; img.data[4 * i + 2] = v; img.data[4 * i + 3] = 255;
    }
    const tmp = el("canvas", { width: cols, height: rows });
    tmp.getContext("2d").putImageData(img, 0, 0);
    // the longer drive gets 520 pixels, the other its share (frames keep their aspect)
    const side = 520, f0 = m.frames[0], f1 = m.frames[1];
    canvas.width = Math.max(60, Math.round(f1 >= f0 ? side : side * f1 / f0));
    canvas.height = Math.max(60, Math.round(f0 >= f1 ? side : side * f0 / f1));
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.imageSmoothingEnabled = false;
    const W = canvas.width, H = canvas.height;
    ctx.drawImage(tmp, 0, 0, W, H);
    // decisions: (frame of this drive, image of the other), on the full-length axes
    const d = m.decisions;
    for (let k = 0; k < d.frame.length; k++) {
      ctx.fillStyle = d.by_self[k] ? "#e53935" : "#1e88e5";
      const x = (d.image[k] + 0.5) / m.frames[1] * W, y = (d.frame[k] + 0.5) / m.frames[0] * H;
      ctx.fillRect(x - 1.5, y - 1.5, 3, 3);
    }
  }

  function setupMatrixEvents() {
    $("matrix-canvas").addEventListener("mousemove", async (ev) => {
      if (!matrix || !drive || !drive.thumbnails) return;
      const r = ev.target.getBoundingClientRect();
      const i = Math.floor((ev.clientY - r.top) / r.height * matrix.frames[0]);
      const j = Math.floor((ev.clientX - r.left) / r.width * matrix.frames[1]);
      showThumb("thumb-a", drive.seq_id, i);
      showThumb("thumb-b", matrix.other, j);
    });
  }
  const thumbUrls = new Map();
  async function showThumb(id, seq, image) {
    const key = seq + "/" + image;
    try {
      if (!thumbUrls.has(key)) thumbUrls.set(key, URL.createObjectURL(await api(`/thumbnails/${seq}/${image}`)));
      $(id).src = thumbUrls.get(key);
      $(id + "-cap").textContent = `sequence ${seq}, image ${image}`;
    } catch (e) {
      $(id).removeAttribute("src");
      $(id + "-cap").textContent = `sequence ${seq}, image ${image}: no thumbnail`;
    }
  }

  // --- trace playback ---------------------------------------------------------------------------
  let tl = null, frame = 0, playing = null;
  const pages = new Map();
  async function loadTrace() {
    if (!ov.trace) return;
    tl = await api("/trace");
    const tab = document.querySelector('nav .tab[data-tab="trace"]');
    tab.hidden = false;
    const m = tl.meta;
    $("trace-info").textContent = `${m.command || "trace"} of ${m.source || "a drive"}: ${tl.frames} frames, ` +
      `k = ${m.k}, top ${m.top_n} states per frame` + (m.smoothed ? "; reported decisions smoothed" : "");
    const slider = $("frame-slider");
    slider.max = Math.max(0, tl.frames - 1);
    slider.oninput = () => setFrame(Number(slider.value));
    $("play").onclick = togglePlay;
    $("timeline-canvas").addEventListener("click", (ev) => {
      const r = ev.target.getBoundingClientRect();
      setFrame(Math.floor((ev.clientX - r.left) / r.width * tl.frames));
    });
  }
  function togglePlay() {
    if (playing) { clearInterval(playing); playing = null; $("play").textContent = "Play"; return; }
    $("play").textContent = "Pause";
    playing = setInterval(() => {
      if (frame >= tl.frames - 1) { togglePlay(); return; }
      setFrame(frame + 1);
    }, 80);
  }
  async function frameData(t) {
    const page = Math.floor(t / 200);
    if (!pages.has(page)) pages.set(page, api(`/trace/frames?start=${page * 200}&count=200`));
    const data = await pages.get(page);
    return data.frames[t - page * 200];
  }
  async function setFrame(t) {
    if (!tl || !tl.frames) return;
    frame = Math.max(0, Math.min(tl.frames - 1, t));
    $("frame-slider").value = frame;
    drawTimeline();
    const f = await frameData(frame);
    if (f.frame !== frame) return; // a later frame was asked meanwhile
    renderFrame(f);
    V.traceFrame = frame;
  }
  function drawTrace() {
    if (!tl) return;
    drawTimeline();
    setFrame(frame);
  }
  function drawTimeline() {
    const [ctx, w, h] = fitCanvas($("timeline-canvas"));
    ctx.clearRect(0, 0, w, h);
    const n = tl.frames, act = tl.n_active_vertices, amax = Math.max(1, ...act);
    const x = (i) => (i + 0.5) / n * w;
    ctx.fillStyle = "rgba(67,160,71,0.25)";
    for (let i = 0; i < n; i++) if (tl.merged[i]) ctx.fillRect(x(i) - w / n / 2, 0, Math.max(1, w / n), h);
    const line = (vals, scale, colour) => {
      ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.beginPath();
      vals.forEach((v, i) => (i ? ctx.lineTo(x(i), h - 4 - v * scale) : ctx.moveTo(x(i), h - 4 - v * scale)));
      ctx.stroke();
    };
    line(act, (h - 8) / amax, "#8e24aa");
    line(tl.dec_prob, h - 8, "#e53935");
    line(tl.novel_prob, h - 8, "#fb8c00");
    ctx.strokeStyle = "#000"; ctx.beginPath(); ctx.moveTo(x(frame), 0); ctx.lineTo(x(frame), h); ctx.stroke();
    ctx.fillStyle = "#333"; ctx.font = "11px sans-serif";
    ctx.fillText(`active vertices (max ${amax})`, 6, 12);
    ctx.fillStyle = "#e53935"; ctx.fillText("decision probability", 160, 12);
    ctx.fillStyle = "#fb8c00"; ctx.fillText("unmapped-place probability", 290, 12);
    ctx.fillStyle = "#43a047"; ctx.fillText("merged (green band)", 460, 12);
  }
  const place = (d) => (d.seq === null ? "no match" : `sequence ${d.seq}, image ${d.image}`);
  function renderFrame(f) {
    $("frame-label").textContent = `frame ${f.frame} / ${tl.frames - 1}`;
    const box = $("frame-detail");
    box.textContent = "";
    box.append(
      el("p", { textContent: `Decision: ${place(f.decision)}, p = ${f.decision.prob.toFixed(3)} ` +
        `(unmapped place ${f.decision.novel_prob.toFixed(3)})` }),
      el("p", { textContent: `Reported: ${place(f.final)}, p = ${f.final.prob.toFixed(3)}` +
        (f.final.merged ? " · merged as an edge" : "") }),
      el("p", { textContent: `Active set: ${f.active.component.length} components, ${f.n_active_vertices} vertices propagated` }));
    const t = el("table", { id: "top-states" },
      el("thead", {}, el("tr", {}, el("th", { textContent: "state (sequence, image)" }), el("th", { textContent: "posterior" }))));
    const tb = el("tbody");
    for (let i = 0; i < f.top.seq.length; i++) {
      tb.append(el("tr", {}, el("td", { textContent: `${f.top.seq[i]}, ${f.top.image[i]}` }),
        el("td", {}, el("span", { className: "bar", style: `width:${Math.round(120 * f.top.prob[i])}px` }),
          " " + f.top.prob[i].toFixed(3))));
    }
    t.append(tb);
    box.append(t);
    const ct = el("p", { textContent: "Components: " + f.active.component.map((c, i) =>
      `${c} (${f.active.mass[i].toFixed(3)})`).join(", ") });
    box.append(ct);
    drawBelief(f);
  }
  function drawBelief(f) {
    const canvas = $("belief-canvas"), ctx = canvas.getContext("2d");
    const W = canvas.width, H = canvas.height;
    ctx.clearRect(0, 0, W, H);
    if (!ov || ov.mode !== "positions" || !f.top.xy) {
      ctx.fillStyle = "#777"; ctx.fillText("(belief map: the map has no positions)", 10, 20);
      return;
    }
    // the drives, faint, then the top states as discs sized by their posterior
    const g = ov.grid, s = 0.94 * Math.min(W, H) / g, o = 0.03 * Math.min(W, H);
    const bx = ov.bbox, span = bx[2] - bx[0];
    ctx.strokeStyle = "rgba(0,0,0,0.12)"; ctx.lineWidth = 1.5;
    for (let q = 0; q < ov.sequences.id.length; q++) {
      const n = ov.points[q], p0 = pointStart[q];
      if (!n) continue;
      ctx.beginPath();
      for (let k = 0; k < n; k++) {
        const X = o + ov.xy[p0 + 2 * k] * s, Y = H - o - ov.xy[p0 + 2 * k + 1] * s;
        k ? ctx.lineTo(X, Y) : ctx.moveTo(X, Y);
      }
      ctx.stroke();
    }
    for (let i = f.top.seq.length - 1; i >= 0; i--) {
      const xy = f.top.xy[i];
      if (!xy) continue;
      const X = o + (xy[0] - bx[0]) / span * g * s, Y = H - o - (xy[1] - bx[1]) / span * g * s;
      const sq = seqIndex.get(f.top.seq[i]);
      ctx.fillStyle = css(colourOfComponent(sq === undefined ? -1 : ov.sequences.component[sq]), 0.75);
      ctx.beginPath(); ctx.arc(X, Y, 3 + 14 * Math.sqrt(f.top.prob[i]), 0, 2 * Math.PI); ctx.fill();
    }
  }

  // --- start -----------------------------------------------------------------------------------
  window.addEventListener("error", (ev) => V.errors.push(String(ev.message)));
  window.addEventListener("unhandledrejection", (ev) => { V.errors.push(String(ev.reason)); fail(ev.reason); });
  setupOverviewEvents();
  setupMatrixEvents();
  V.openDrive = openDrive;
  V.openMatrix = openMatrix;
  V.setFrame = setFrame;
  V.showTab = showTab;
  loadOverview().then(loadTrace).then(() => { V.ready = true; }).catch(fail);
})();
