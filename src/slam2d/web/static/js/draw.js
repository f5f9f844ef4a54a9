// Shared drawing on <canvas>: a world view (metres, y up) fitted to the page's world bounds, and a heat map.
// Everything drawn here was computed by the library on the server; this module only turns numbers into pixels.

export const COLORS = {
  wall: '#555', trueLm: '#222', truePath: '#2a9d3a', robot: '#2a9d3a', estPath: '#1f5fbf', estRobot: '#1f5fbf',
  estLm: '#d62828', ellipse: 'rgba(31,95,191,0.75)', obs: 'rgba(240,140,0,0.55)', obsEllipse: 'rgba(240,140,0,0.8)',
  particle: 'rgba(140,60,180,0.55)', good: '#2a9d3a', bad: '#d62828', newObs: '#888', scan: '#444',
  graphEdge: 'rgba(31,95,191,0.18)', graphNode: '#1f5fbf', feature: '#d62828', trueCorner: '#2a9d3a',
  ghost: 'rgba(120,120,120,0.75)', range: 'rgba(240,140,0,0.35)',
};

// Does each section of `cur` start with the rows of its copy in `old` (same numbers), with at most `extra` more
// rows? (A cached layer drawn from `old` is then still right; the extra rows are drawn over it.)
function extendsSections(old, cur, extra) {
  if (old.length !== cur.length) return false;
  for (let i = 0; i < old.length; i++) {
    const x = old[i], y = cur[i];
    if (!x || !y) { if (Boolean(x) !== Boolean(y) || (x && x.rows)) return false; continue; }
    if (x.cols !== y.cols || y.rows < x.rows || y.rows - x.rows > extra) return false;
    const p = x.data, q = y.data;
    for (let j = 0; j < p.length; j++) if (p[j] !== q[j]) return false;
  }
  return true;
}

export class WorldView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext('2d');
    this.bounds = [0, 0, 10, 10];
    this.layers = {}; // cached layers (cached())
    this.fit();
  }

  // A layer drawn from sections that often stay the same for many frames (the background; the paths; a graph back
  // end's landmarks between two optimisations): once they have stayed the same (with the view) for `settle` frames
  // in a row, the layer is drawn into an offscreen canvas and copied from there (one drawImage) until they change.
  // Options: `append` rows may be added to the sections and are drawn directly over the copy (at most 64, then the
  // layer is redrawn); the last `live` rows of each section are never cached (a path's newest point moves every
  // frame). Sections that change every frame (an EKF's landmarks) are drawn directly, at the cost of a comparison.
  // drawFn(from, to) draws rows from[i]..to[i]-1 of section i and returns a count (summed over the two parts).
  cached(name, secs, settle, drawFn, { append = false, live = 0 } = {}) {
    const view = [this.scale, this.ox, this.oy, this.canvas.width, this.canvas.height];
    const L = this.layers[name] || (this.layers[name] = { secs: null, view: null, same: 0, ready: false, off: null });
    const rows = secs.map((x) => (x ? x.rows : 0));
    const extra = append ? 64 + live : live;
    if (L.secs && L.view.every((v, i) => v === view[i]) && extendsSections(L.secs, secs, extra)) {
      L.same += 1;
    } else {
      // copies of the rows to cache: the sections' arrays are views into a frame buffer the next frame replaces
      L.secs = secs.map((x) => {
        if (!x) return x;
        const r = Math.max(x.rows - live, 0);
        return { rows: r, cols: x.cols, data: x.data.slice(0, r * x.cols) };
      });
      L.view = view; L.same = 0; L.ready = false;
    }
    const c = this.ctx, zero = rows.map(() => 0);
    if (L.same < settle) return drawFn(zero, rows);
    const kept = L.secs.map((x) => (x ? x.rows : 0));
    if (!L.ready) {
      if (!L.off || L.off.width !== this.canvas.width || L.off.height !== this.canvas.height) {
        L.off = new OffscreenCanvas(this.canvas.width, this.canvas.height);
      }
      this.ctx = L.off.getContext('2d');
      try {
        this.ctx.setTransform(1, 0, 0, 1, 0, 0);
        this.ctx.clearRect(0, 0, L.off.width, L.off.height);
        L.result = drawFn(zero, kept);
      } finally {
        this.ctx = c;
      }
      L.ready = true;
    }
    c.setTransform(1, 0, 0, 1, 0, 0);
    c.drawImage(L.off, 0, 0);
    return rows.some((r, i) => r > kept[i]) ? (L.result || 0) + drawFn(kept, rows) : L.result;
  }

  // the background: white, the grid image, the walls (when there is no grid) and the true landmarks
  base(s) {
    this.cached('base', [s.GRID, s.GRDM, s.WALL, s.TLMK], 0, () => {
      this.clear();
      this.grid(s.GRID, s.GRDM);
      if (!s.GRID) this.segments(s.WALL, COLORS.wall, 2);
      this.crosses(s.TLMK, COLORS.trueLm, 4);
    });
  }

  setBounds(b) {
    if (Array.isArray(b) && b.length === 4) { this.bounds = b; this.fit(); }
  }

  fit() {
    const [x0, y0, x1, y1] = this.bounds;
    const pad = 20;
    const w = this.canvas.width - 2 * pad;
    const h = this.canvas.height - 2 * pad;
    this.scale = Math.min(w / Math.max(x1 - x0, 1e-6), h / Math.max(y1 - y0, 1e-6));
    this.ox = pad + (w - this.scale * (x1 - x0)) / 2 - this.scale * x0;
    this.oy = this.canvas.height - pad - (h - this.scale * (y1 - y0)) / 2 + this.scale * y0;
  }

  px(x) { return this.ox + this.scale * x; }
  py(y) { return this.oy - this.scale * y; }

  clear() {
    const c = this.ctx;
    c.setTransform(1, 0, 0, 1, 0, 0);
    c.fillStyle = '#fff';
    c.fillRect(0, 0, this.canvas.width, this.canvas.height);
  }

  segments(s, color, width = 2) {
    if (!s || s.rows === 0) return;
    const c = this.ctx, d = s.data;
    c.beginPath();
    for (let i = 0; i < s.rows; i++) {
      c.moveTo(this.px(d[4 * i]), this.py(d[4 * i + 1]));
      c.lineTo(this.px(d[4 * i + 2]), this.py(d[4 * i + 3]));
    }
    c.strokeStyle = color; c.lineWidth = width; c.stroke();
  }

  // a polyline through rows from..to-1 (one path, one stroke)
  path(s, color, width = 2, dash = [], from = 0, to = Infinity) {
    const end = s ? Math.min(s.rows, to) : 0;
    if (end - from < 2) return;
    const c = this.ctx, d = s.data;
    c.beginPath();
    c.moveTo(this.px(d[2 * from]), this.py(d[2 * from + 1]));
    for (let i = from + 1; i < end; i++) c.lineTo(this.px(d[2 * i]), this.py(d[2 * i + 1]));
    c.setLineDash(dash); c.strokeStyle = color; c.lineWidth = width; c.stroke(); c.setLineDash([]);
  }

  // points as small squares (fast: one path, one fill)
  dots(s, color, size = 4, stride = null, from = 0, to = Infinity) {
    if (!s || s.rows === 0) return;
    const c = this.ctx, d = s.data, k = stride || s.cols, h = size / 2, end = Math.min(s.rows, to);
    c.beginPath();
    for (let i = from; i < end; i++) c.rect(this.px(d[k * i]) - h, this.py(d[k * i + 1]) - h, size, size);
    c.fillStyle = color; c.fill();
  }

  crosses(s, color, size = 4) {
    if (!s || s.rows === 0) return;
    const c = this.ctx, d = s.data;
    c.beginPath();
    for (let i = 0; i < s.rows; i++) {
      const x = this.px(d[2 * i]), y = this.py(d[2 * i + 1]);
      c.moveTo(x - size, y - size); c.lineTo(x + size, y + size);
      c.moveTo(x - size, y + size); c.lineTo(x + size, y - size);
    }
    c.strokeStyle = color; c.lineWidth = 1.5; c.stroke();
  }

  robot(p, color, r = 0.45) {
    if (!p || p.rows === 0) return;
    const [x, y, th] = p.data;
    const c = this.ctx, s = this.scale * r;
    const cx = this.px(x), cy = this.py(y);
    c.beginPath();
    c.moveTo(cx + 1.6 * s * Math.cos(th), cy - 1.6 * s * Math.sin(th));
    c.lineTo(cx + s * Math.cos(th + 2.4), cy - s * Math.sin(th + 2.4));
    c.lineTo(cx + s * Math.cos(th - 2.4), cy - s * Math.sin(th - 2.4));
    c.closePath();
    c.fillStyle = color; c.fill();
  }

  // a circle: centre x, y and radius (m), e.g. the sensor's range around the robot
  circle(s, color) {
    if (!s || s.rows === 0) return;
    const [x, y, r] = s.data, c = this.ctx;
    c.beginPath();
    c.arc(this.px(x), this.py(y), Math.max(this.scale * r, 0), 0, 2 * Math.PI);
    c.setLineDash([4, 4]); c.strokeStyle = color; c.lineWidth = 1; c.stroke(); c.setLineDash([]);
  }

  // rays from a pose to points
  rays(pose, pts, color) {
    if (!pose || !pts || pts.rows === 0) return;
    const c = this.ctx, d = pts.data, x = this.px(pose.data[0]), y = this.py(pose.data[1]);
    c.beginPath();
    for (let i = 0; i < pts.rows; i++) { c.moveTo(x, y); c.lineTo(this.px(d[2 * i]), this.py(d[2 * i + 1])); }
    c.strokeStyle = color; c.lineWidth = 1; c.stroke();
  }

  // 95% ellipses of 2x2 covariances (row-major, 4 per row) centred on means (2 per row); all in one path.
  // The 2x2 eigen-decomposition is closed form; k = sqrt(chi2_2(0.95)) = sqrt(5.991). Each ellipse gets as many
  // segments as its size in pixels needs (chord error about 1/4 px: n = pi sqrt(2 r), 8..24), and one whose
  // major semi-axis is under minPx pixels is not stroked: it would lie inside the landmark's 5-pixel dot.
  ellipses(means, covs, color, meanStride = 2, minPx = 2, from = 0, to = Infinity) {
    if (!means || !covs || covs.rows === 0) return 0;
    const c = this.ctx, m = means.data, v = covs.data, n = Math.min(means.rows, covs.rows, to);
    const k = Math.sqrt(5.991), sc = this.scale;
    let drawn = 0;
    c.beginPath();
    for (let i = from; i < n; i++) {
      const a = v[4 * i], b = 0.5 * (v[4 * i + 1] + v[4 * i + 2]), d = v[4 * i + 3];
      const mean = 0.5 * (a + d), rad = Math.sqrt(Math.max(0.25 * (a - d) * (a - d) + b * b, 0));
      const l1 = Math.sqrt(Math.max(mean + rad, 0)) * k, l2 = Math.sqrt(Math.max(mean - rad, 0)) * k;
      const r = l1 * sc;
      if (!(r >= minPx)) continue; // tiny (or NaN)
      const seg = Math.min(24, Math.max(8, Math.ceil(Math.PI * Math.sqrt(2 * r))));
      const ang = 0.5 * Math.atan2(2 * b, a - d), ca = Math.cos(ang), sa = Math.sin(ang);
      const X0 = this.px(m[meanStride * i]), Y0 = this.py(m[meanStride * i + 1]);
      // in pixels: x right, y down (the world's y axis flipped)
      const ux = sc * l1 * ca, uy = -sc * l1 * sa, vx = -sc * l2 * sa, vy = -sc * l2 * ca;
      c.moveTo(X0 + ux, Y0 + uy);
      for (let j = 1; j <= seg; j++) {
        const t = (2 * Math.PI * j) / seg, ct = Math.cos(t), st = Math.sin(t);
        c.lineTo(X0 + ct * ux + st * vx, Y0 + ct * uy + st * vy);
      }
      drawn += 1;
    }
    c.strokeStyle = color; c.lineWidth = 1; c.stroke();
    return drawn;
  }

  // association lines: x,y (observation), x,y (landmark), flag (1 correct, 0 wrong)
  matches(s) {
    if (!s || s.rows === 0) return;
    const c = this.ctx, d = s.data;
    for (const ok of [1, 0]) {
      c.beginPath();
      for (let i = 0; i < s.rows; i++) {
        if ((d[5 * i + 4] > 0.5 ? 1 : 0) !== ok) continue;
        c.moveTo(this.px(d[5 * i]), this.py(d[5 * i + 1]));
        c.lineTo(this.px(d[5 * i + 2]), this.py(d[5 * i + 3]));
      }
      c.strokeStyle = ok ? COLORS.good : COLORS.bad; c.lineWidth = ok ? 1.5 : 2.5; c.stroke();
    }
  }
}

// a grid image (values in [0,1], row 0 = lowest y) placed in the world: meta = [origin x, origin y, cell size]
WorldView.prototype.grid = function grid(g, meta) {
  if (!g || !meta || g.rows === 0) return;
  const rows = g.rows, cols = g.cols, d = g.data, img = new ImageData(cols, rows);
  for (let r = 0; r < rows; r++) {
    const dst = (rows - 1 - r) * cols; // flip: canvas rows grow downwards, world y grows upwards
    for (let c = 0; c < cols; c++) {
      const v = 255 - Math.round(255 * Math.min(Math.max(d[r * cols + c], 0), 1)), k = 4 * (dst + c);
      img.data[k] = v; img.data[k + 1] = v; img.data[k + 2] = v; img.data[k + 3] = 255;
    }
  }
  const off = new OffscreenCanvas(cols, rows);
  off.getContext('2d').putImageData(img, 0, 0);
  const [x0, y0, res] = meta.data;
  const c = this.ctx;
  c.imageSmoothingEnabled = false;
  c.drawImage(off, this.px(x0), this.py(y0 + rows * res), cols * res * this.scale, rows * res * this.scale);
};

// |correlation| matrix as an image: white 0 .. dark blue 1; drawn through a small offscreen ImageData
export function drawHeat(canvas, s) {
  const c = canvas.getContext('2d');
  c.fillStyle = '#fff'; c.fillRect(0, 0, canvas.width, canvas.height);
  if (!s || s.rows === 0) return;
  const n = s.rows, img = new ImageData(n, n), d = s.data;
  for (let i = 0; i < n * n; i++) {
    const v = Math.min(Math.max(d[i], 0), 1);
    img.data[4 * i] = 255 - 224 * v; img.data[4 * i + 1] = 255 - 160 * v; img.data[4 * i + 2] = 255 - 64 * v;
    img.data[4 * i + 3] = 255;
  }
  const off = new OffscreenCanvas(n, n);
  off.getContext('2d').putImageData(img, 0, 0);
  c.imageSmoothingEnabled = false;
  c.drawImage(off, 0, 0, canvas.width, canvas.height);
}

// The particle cloud magnified: particles relative to their mean, scaled so the cloud fills about half the inset,
// with the true pose (green) and a labelled scale bar. Returns {spreadPx, metresPerPx} for the page's test hooks.
export function drawParticleZoom(canvas, parts, truePose) {
  const c = canvas.getContext('2d'), W = canvas.width, H = canvas.height;
  c.fillStyle = '#fff'; c.fillRect(0, 0, W, H);
  c.strokeStyle = '#ccc'; c.strokeRect(0.5, 0.5, W - 1, H - 1);
  if (!parts || parts.rows === 0) return null;
  const d = parts.data, k = parts.cols, n = parts.rows;
  let mx = 0, my = 0;
  for (let i = 0; i < n; i++) { mx += d[k * i]; my += d[k * i + 1]; }
  mx /= n; my /= n;
  let r = 0;
  for (let i = 0; i < n; i++) r = Math.max(r, Math.hypot(d[k * i] - mx, d[k * i + 1] - my));
  const extent = Math.max(r, 0.002); // metres from the mean to the farthest particle (2 mm floor)
  const scale = (0.45 * Math.min(W, H)) / extent; // pixels per metre
  const px = (x) => W / 2 + scale * (x - mx), py = (y) => H / 2 - scale * (y - my);
  c.fillStyle = COLORS.particle;
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (let i = 0; i < n; i++) {
    const X = px(d[k * i]), Y = py(d[k * i + 1]);
    c.fillRect(X - 2, Y - 2, 4, 4);
    x0 = Math.min(x0, X); x1 = Math.max(x1, X); y0 = Math.min(y0, Y); y1 = Math.max(y1, Y);
  }
  if (truePose && truePose.rows) {
    const X = px(truePose.data[0]), Y = py(truePose.data[1]);
    c.strokeStyle = COLORS.robot; c.lineWidth = 2;
    c.beginPath(); c.moveTo(X - 6, Y); c.lineTo(X + 6, Y); c.moveTo(X, Y - 6); c.lineTo(X, Y + 6); c.stroke();
  }
  // scale bar: the round length (1, 2 or 5 x 10^k m) nearest a quarter of the inset
  const target = (0.25 * W) / scale, p10 = Math.pow(10, Math.floor(Math.log10(target)));
  const len = [1, 2, 5, 10].map((m) => m * p10).reduce((a, b) => (Math.abs(b - target) < Math.abs(a - target) ? b : a));
  const bar = len * scale;
  c.strokeStyle = '#222'; c.lineWidth = 2;
  c.beginPath(); c.moveTo(10, H - 12); c.lineTo(10 + bar, H - 12); c.stroke();
  c.fillStyle = '#222'; c.font = '12px system-ui, sans-serif';
  const label = len >= 1 ? `${len} m` : len >= 0.01 ? `${Math.round(len * 100)} cm` : `${Math.round(len * 1000)} mm`;
  c.fillText(label, 14 + bar, H - 8);
  return { spreadPx: Math.max(x1 - x0, y1 - y0), metresPerPx: 1 / scale, barLabel: label };
}
