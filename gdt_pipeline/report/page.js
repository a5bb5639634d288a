// gdt report: draws the embedded figures with the embedded plotly.js; nothing is fetched.
(function () {
  "use strict";
  const data = JSON.parse(document.getElementById("gdt-data").textContent);
  const config = {displaylogo: false, responsive: true, scrollZoom: true};
  const view = document.getElementById("view3d");
  const boxIndex = data.view.data.length - 1;  // the segment box is the last trace

  // one (state, epoch) layer per trace: visible when both its state and its epoch are ticked
  function applyToggles() {
    const on = {};
    document.querySelectorAll("input[data-toggle]").forEach(function (box) {
      on[box.dataset.toggle + ":" + box.value] = box.checked;
    });
    const idx = [], vis = [];
    view.data.forEach(function (trace, i) {
      if (!trace.meta || i === boxIndex) return;
      idx.push(i);
      vis.push(on["state:" + trace.meta.state] !== false && on["epoch:" + trace.meta.epoch] !== false);
    });
    if (idx.length) Plotly.restyle(view, {visible: vis}, idx);
  }

  // the 12 edges of an axis-aligned box as one polyline with breaks
  function boxEdges(lo, hi) {
    const c = [0, 1, 2, 3, 4, 5, 6, 7].map(function (k) {
      return [(k & 1) ? hi[0] : lo[0], (k & 2) ? hi[1] : lo[1], (k & 4) ? hi[2] : lo[2]];
    });
    const edges = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];
    const out = {x: [], y: [], z: []};
    edges.forEach(function (e) {
      ["x", "y", "z"].forEach(function (a, i) { out[a].push(c[e[0]][i], c[e[1]][i], null); });
    });
    return out;
  }

  function frame(ranges) {
    const update = {"scene.aspectmode": "cube", "scene.camera": data.view.layout.scene.camera};
    ["x", "y", "z"].forEach(function (a) { update["scene." + a + "axis.range"] = ranges[a + "axis"]; });
    return Plotly.relayout(view, update);
  }

  // a segment: its box drawn, the view framed on it (a cube around the box with a margin)
  function showSegment(row) {
    const seg = data.segments[row.dataset.segment];
    if (!seg) return;
    document.querySelectorAll("#segments tr.selected").forEach(function (r) { r.classList.remove("selected"); });
    row.classList.add("selected");
    const lo = seg.lower, hi = seg.upper, ranges = {};
    const half = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) * 0.75 + data.view.margin;
    ["x", "y", "z"].forEach(function (a, i) {
      const mid = (lo[i] + hi[i]) / 2;
      ranges[a + "axis"] = [mid - half, mid + half];
    });
    const edges = boxEdges(lo, hi);
    Plotly.restyle(view, {x: [edges.x], y: [edges.y], z: [edges.z], visible: true}, [boxIndex]);
    frame(ranges);
    document.getElementById("view").scrollIntoView({block: "start"});
  }

  const drawn = [Plotly.newPlot(view, data.view.data, data.view.layout, config)];
  data.histograms.forEach(function (h) {
    drawn.push(Plotly.newPlot(document.getElementById(h.id), h.figure.data, h.figure.layout, config));
  });
  Promise.all(drawn).then(function () {
    document.querySelectorAll("input[data-toggle]").forEach(function (box) {
      box.addEventListener("change", applyToggles);
    });
    document.querySelectorAll("#segments tr[data-segment]").forEach(function (row) {
      row.addEventListener("click", function () { showSegment(row); });
      row.addEventListener("keydown", function (ev) { if (ev.key === "Enter") showSegment(row); });
    });
    document.getElementById("home").addEventListener("click", function () {
      document.querySelectorAll("#segments tr.selected").forEach(function (r) { r.classList.remove("selected"); });
      Plotly.restyle(view, {visible: false}, [boxIndex]);
      frame(data.view.home);
    });
    // WebGL draws on the next animation frames: ready once two have passed
    requestAnimationFrame(function () {
      requestAnimationFrame(function () { window.gdtReportReady = true; });
    });
  });
})();
