"use strict";
// partinspect report: click-to-enlarge images and the 3D viewer (orthographic canvas, no library).
(function () {
  document.querySelectorAll(".photo-panel").forEach(function (p) {
    p.addEventListener("click", function () { p.classList.toggle("big"); });
  });

  var data = document.getElementById("scene-data");
  var root = document.getElementById("viewer3d");
  if (!data || !root) { return; }
  var S = JSON.parse(data.textContent);
  var canvas = root.querySelector("canvas");
  var tip = root.querySelector(".viewer-tip");
  var ctx = canvas.getContext("2d");
  var c0 = S.center, ext = S.extent || 1;
  var M, zoom, pan, mag = S.mag || 0;
  var firstView = Object.keys(S.views)[0];

  function setView(name) {
    M = S.views[name].map(function (r) { return r.slice(); });
    zoom = 1; pan = [0, 0];
    fit();
    draw();
  }
  function fit() {
    // Frame what is drawn: the projected bounding box fills 90 % of the canvas, centred.
    var wh = size(), lo = [Infinity, Infinity], hi = [-Infinity, -Infinity];
    var each = function (p) {
      var x = p[0] - c0[0], y = p[1] - c0[1], z = p[2] - c0[2];
      for (var i = 0; i < 2; i++) {
        var v = M[i][0] * x + M[i][1] * y + M[i][2] * z;
        lo[i] = Math.min(lo[i], v); hi[i] = Math.max(hi[i], v);
      }
    };
    S.edges.forEach(function (e) { e.p.forEach(each); });
    S.features.forEach(function (f) { f.p.forEach(each); });
    if (!(hi[0] >= lo[0])) { return; }
    var base = 0.86 * Math.min(wh[0], wh[1]) / ext;
    var sx = (hi[0] - lo[0]) * base, sy = (hi[1] - lo[1]) * base;
    zoom = Math.min(0.9 * wh[0] / Math.max(sx, 1e-9), 0.9 * wh[1] / Math.max(sy, 1e-9));
    pan = [-(lo[0] + hi[0]) / 2 * base * zoom, -(lo[1] + hi[1]) / 2 * base * zoom];
  }
  function mul(A, B) {
    var C = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
    for (var i = 0; i < 3; i++) for (var j = 0; j < 3; j++)
      C[i][j] = A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j];
    return C;
  }
  function rot(axis, a) {
    var c = Math.cos(a), s = Math.sin(a);
    return axis === 0 ? [[1, 0, 0], [0, c, -s], [0, s, c]] : [[c, 0, s], [0, 1, 0], [-s, 0, c]];
  }
  function orthonormalize() {
    // Gram-Schmidt on the rows, so that rounding never shears the view.
    var a = M[0], b = M[1];
    var na = Math.hypot(a[0], a[1], a[2]); a = a.map(function (v) { return v / na; });
    var d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    b = [b[0] - d * a[0], b[1] - d * a[1], b[2] - d * a[2]];
    var nb = Math.hypot(b[0], b[1], b[2]); b = b.map(function (v) { return v / nb; });
    M = [a, b, [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]];
  }
  function size() {
    var w = Math.max(200, Math.round(root.clientWidth || 800));
    var h = Math.round(w * 0.56);
    var r = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * r)) {
      canvas.width = Math.round(w * r); canvas.height = Math.round(h * r);
      canvas.style.width = w + "px"; canvas.style.height = h + "px";
    }
    ctx.setTransform(r, 0, 0, r, 0, 0);
    return [w, h];
  }
  var W = 0, H = 0, s = 1;
  function proj(p) {
    var x = p[0] - c0[0], y = p[1] - c0[1], z = p[2] - c0[2];
    return [W / 2 + pan[0] + s * (M[0][0] * x + M[0][1] * y + M[0][2] * z),
            H / 2 + pan[1] + s * (M[1][0] * x + M[1][1] * y + M[1][2] * z)];
  }
  var hits = [];
  function draw() {
    var wh = size(); W = wh[0]; H = wh[1];
    s = 0.86 * Math.min(W, H) / ext * zoom;
    ctx.clearRect(0, 0, W, H);
    ctx.fillStyle = "#fbfcfd"; ctx.fillRect(0, 0, W, H);
    ctx.lineJoin = "round";
    ctx.strokeStyle = "#8a93a3"; ctx.lineWidth = 1;
    S.edges.forEach(function (e) {
      ctx.beginPath();
      e.p.forEach(function (p, i) { var q = proj(p); if (i) ctx.lineTo(q[0], q[1]); else ctx.moveTo(q[0], q[1]); });
      ctx.stroke();
    });
    hits = [];
    var f2 = Math.pow(S.k * mag * s, 2);
    S.features.forEach(function (f) {
      var col = S.colours[f.status] || "#333";
      if (mag > 0) {
        ctx.fillStyle = col; ctx.strokeStyle = col; ctx.lineWidth = 0.8;
        f.ep.forEach(function (p, i) {
          var c = f.ec[i];
          var C = [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]];
          // Outline of the projected ellipsoid: the 2x2 block of M C M^T (orthographic).
          var P = mul(mul(M, C), [[M[0][0], M[1][0], M[2][0]], [M[0][1], M[1][1], M[2][1]], [M[0][2], M[1][2], M[2][2]]]);
          var a = P[0][0] * f2, b = P[0][1] * f2, d = P[1][1] * f2;
          var m = (a + d) / 2, r = Math.sqrt(Math.max(0, (a - d) * (a - d) / 4 + b * b));
          var l1 = Math.sqrt(Math.max(m + r, 0)), l2 = Math.sqrt(Math.max(m - r, 0));
          var q = proj(p);
          ctx.beginPath();
          ctx.ellipse(q[0], q[1], Math.max(l1, 0.5), Math.max(l2, 0.5), 0.5 * Math.atan2(2 * b, a - d), 0, 2 * Math.PI);
          ctx.globalAlpha = 0.18; ctx.fill(); ctx.globalAlpha = 0.7; ctx.stroke(); ctx.globalAlpha = 1;
        });
      }
      ctx.fillStyle = col;
      f.p.forEach(function (p) {
        var q = proj(p);
        ctx.fillRect(q[0] - 1.2, q[1] - 1.2, 2.4, 2.4);
        hits.push([q[0], q[1], f]);
      });
    });
    triad();
    scalebar();
  }
  function triad() {
    var o = [34, H - 34], L = 22, names = ["X", "Y", "Z"], cols = ["#c2412d", "#2f9e6e", "#3b6fb6"];
    ctx.font = "11px system-ui, sans-serif"; ctx.lineWidth = 1.6;
    for (var j = 0; j < 3; j++) {
      var dx = M[0][j] * L, dy = M[1][j] * L;
      ctx.strokeStyle = cols[j]; ctx.fillStyle = cols[j];
      ctx.beginPath(); ctx.moveTo(o[0], o[1]); ctx.lineTo(o[0] + dx, o[1] + dy); ctx.stroke();
      ctx.fillText(names[j], o[0] + dx * 1.25 - 3, o[1] + dy * 1.25 + 4);
    }
  }
  function scalebar() {
    var target = 120 / s, e = Math.pow(10, Math.floor(Math.log10(target))), m = target / e;
    var len = (m >= 5 ? 5 : m >= 2 ? 2 : 1) * e, px = len * s;
    var x = W - 20 - px, y = H - 22;
    ctx.strokeStyle = "#1d2330"; ctx.fillStyle = "#1d2330"; ctx.lineWidth = 1.5;
    ctx.beginPath(); ctx.moveTo(x, y - 4); ctx.lineTo(x, y); ctx.lineTo(x + px, y); ctx.lineTo(x + px, y - 4); ctx.stroke();
    ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "center";
    ctx.fillText(len + " mm", x + px / 2, y - 6);
    if (mag > 0) { ctx.textAlign = "right"; ctx.fillText("ellipsoids ×" + mag, W - 20, 18); }
    ctx.textAlign = "start";
  }

  var sel = root.querySelector("select[data-mag]");
  if (mag > 0) {
    [mag / 10, mag / 5, mag / 2, mag, mag * 2, mag * 5, mag * 10].forEach(function (v) {
      v = Number(v.toPrecision(3));
      var o = document.createElement("option"); o.value = String(v); o.textContent = String(v);
      if (v === mag) o.selected = true;
      sel.appendChild(o);
    });
    sel.addEventListener("change", function () { mag = Number(sel.value); draw(); });
  } else {
    sel.parentNode.hidden = true;
  }
  root.querySelectorAll("button[data-view]").forEach(function (b) {
    b.addEventListener("click", function () { setView(b.dataset.view === "reset" ? firstView : b.dataset.view); });
  });

  var drag = null;
  canvas.addEventListener("pointerdown", function (ev) {
    drag = [ev.clientX, ev.clientY, ev.shiftKey];
    if (canvas.setPointerCapture) { try { canvas.setPointerCapture(ev.pointerId); } catch (e) { /* synthetic events */ } }
  });
  canvas.addEventListener("pointerup", function () { drag = null; });
  canvas.addEventListener("pointercancel", function () { drag = null; });
  canvas.addEventListener("pointermove", function (ev) {
    if (drag) {
      var dx = ev.clientX - drag[0], dy = ev.clientY - drag[1];
      drag[0] = ev.clientX; drag[1] = ev.clientY;
      if (drag[2]) { pan[0] += dx; pan[1] += dy; }
      else { M = mul(rot(0, -dy * 0.01), mul(rot(1, dx * 0.01), M)); orthonormalize(); }
      draw();
      return;
    }
    var r = canvas.getBoundingClientRect(), x = ev.clientX - r.left, y = ev.clientY - r.top, best = null, bd = 64;
    hits.forEach(function (h) { var d = (h[0] - x) * (h[0] - x) + (h[1] - y) * (h[1] - y); if (d < bd) { bd = d; best = h; } });
    if (best) {
      var f = best[2];
      tip.textContent = (f.label || "unmatched") + ": " + f.status +
        (f.sigma != null ? " · median largest σ " + (f.sigma * 1000).toPrecision(3) + " µm" : "");
      tip.style.left = (x + 12) + "px"; tip.style.top = (y + 12) + "px"; tip.hidden = false;
    } else { tip.hidden = true; }
  });
  canvas.addEventListener("pointerleave", function () { tip.hidden = true; });
  canvas.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    zoom *= Math.exp(-ev.deltaY * 0.0015);
    zoom = Math.min(Math.max(zoom, 0.2), 200);
    draw();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { setView(firstView); });
  window.addEventListener("resize", draw);
  window.addEventListener("beforeprint", draw);
  setView(firstView);
  root.dataset.ready = "1";
})();
