// One lab page: opens the page's websocket, builds its controls from the server's parameter list, shows live
// numbers, and draws the latest frame on every animation frame. Test hooks live on window.slamLab.
import { decodeFrame } from './frames.js';
import { WorldView, drawHeat, drawParticleZoom, COLORS } from './draw.js';

const page = document.body.dataset.page;
const query = new URLSearchParams(location.search);
const canvas = document.getElementById('world');
const view = new WorldView(canvas);
const heatCanvas = document.getElementById('heat');
const zoomCanvas = document.getElementById('zoom');
const statusEl = document.getElementById('status');
const numbersEl = document.getElementById('numbers');
const controlsEl = document.getElementById('controls');
const noticesEl = document.getElementById('notices');
const errorsEl = document.getElementById('errors');

const lab = {
  page, frames: 0, bytes: 0, drawn: 0, fps: 0, recvFps: 0, seq: -1, decodeMs: 0, drawMs: 0,
  pose: null, estPose: null, counters: {}, values: {}, notices: [], errors: [], hello: null, connected: false, states: 0,
  lost: null,
  rows: [], inactive: [], zoom: null, feedback: null,
  sections: {}, record: 0, recorded: null, statusTicks: 0, openedAt: null,
  send: (obj) => send(obj),
  // benchmark hook: draw a recorded frame now (and finish its pixels), without the websocket
  drawBuffer: (buf) => { latest = decodeFrame(buf); draw(); view.ctx.getImageData(0, 0, 1, 1); },
};
window.slamLab = lab;
lab.view = view; // benchmark hook

let ws = null;
// the status while the server builds this page's session (a simulation, a saved map: seconds on a first visit)
const BUILDING = "connected · building this page's session…";
let latest = null;
let drawnSeq = -1;
let scalarNames = [];
let worldBounds = null;

// the view fits the world, and grows (never shrinks) when the estimate drifts outside it, so nothing is clipped
function fitEstimate(s) {
  if (!worldBounds) return;
  const [bx0, by0, bx1, by1] = view.bounds;
  let [x0, y0, x1, y1] = [bx0, by0, bx1, by1];
  for (const sec of [s.EPTH, s.EPOS, s.GHST]) {
    if (!sec) continue;
    for (let i = 0; i < sec.rows; i++) {
      const x = sec.data[sec.cols * i], y = sec.data[sec.cols * i + 1];
      if (x < x0) x0 = x; if (x > x1) x1 = x; if (y < y0) y0 = y; if (y > y1) y1 = y;
    }
  }
  if (x0 < bx0 || y0 < by0 || x1 > bx1 || y1 > by1) {
    const m = 0.05 * Math.max(x1 - x0, y1 - y0);
    view.setBounds([x0 - m, y0 - m, x1 + m, y1 + m]);
  }
}
const paramsByName = {};

function send(obj) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj));
}

function fmt(v) {
  if (v === null || v === undefined || Number.isNaN(v)) return '–';
  if (typeof v !== 'number') return String(v);
  if (Number.isInteger(v)) return String(v);
  return Math.abs(v) >= 100 ? v.toFixed(1) : v.toFixed(3);
}

function buildNumbers(names, labels) {
  numbersEl.innerHTML = '';
  for (const n of names) {
    const row = document.createElement('div');
    row.className = 'num';
    row.dataset.row = n;
    const k = document.createElement('span');
    k.className = 'k';
    k.textContent = (labels && labels[n]) || n;
    const v = document.createElement('span');
    v.className = 'v';
    v.dataset.num = n;
    v.textContent = '–';
    row.append(k, v);
    numbersEl.appendChild(row);
  }
}

function buildControls(params, actions) {
  controlsEl.innerHTML = '';
  for (const p of params) {
    paramsByName[p.name] = p;
    const wrap = document.createElement('label');
    wrap.className = 'ctl';
    wrap.title = p.help || '';
    let input;
    if (p.kind === 'choice') {
      input = document.createElement('select');
      for (const c of p.choices) {
        const o = document.createElement('option');
        o.value = c; o.textContent = c; input.appendChild(o);
      }
    } else if (p.kind === 'bool') {
      input = document.createElement('input');
      input.type = 'checkbox';
    } else if (p.name === 'seed' || p.name === 'landmarks') {
      input = document.createElement('input');
      input.type = 'number'; input.min = p.lo; input.max = p.hi; input.step = p.step || 1;
    } else {
      input = document.createElement('input');
      input.type = 'range'; input.min = p.lo; input.max = p.hi; input.step = p.step || 'any';
    }
    input.id = `ctl-${p.name}`;
    input.dataset.param = p.name;
    const text = document.createElement('span');
    text.className = 'label';
    text.textContent = p.label;
    const out = document.createElement('output');
    out.id = `out-${p.name}`;
    wrap.append(text, input, out);
    controlsEl.appendChild(wrap);
    input.addEventListener('input', () => { editing.add(input); });
    // a slider dragged back to where it was fires no change: the edit ends when it is let go or left
    for (const ev of ['pointerup', 'blur']) input.addEventListener(ev, () => { editing.delete(input); });
    input.addEventListener('change', () => {
      editing.delete(input);
      let value;
      if (input.type === 'number' && input.value.trim() === '') { showValues(); return; } // emptied: not a 0
      if (p.kind === 'bool') value = input.checked;
      else if (p.kind === 'choice') value = input.value;
      else value = Number(input.value);
      send({ type: 'param', name: p.name, value });
    });
    if (input.type === 'range') input.addEventListener('input', () => { out.textContent = fmt(Number(input.value)); });
  }
  for (const a of actions) {
    const b = document.createElement('button');
    b.id = `act-${a.name}`;
    b.textContent = a.label;
    b.addEventListener('click', () => send({ type: 'action', name: a.name }));
    controlsEl.appendChild(b);
  }
}

// the chapter's check question: choices as buttons; the server judges the answer and sends its feedback
function buildCheck(check) {
  if (!check || document.getElementById('check')) return;
  const box = document.createElement('section');
  box.id = 'check';
  box.className = 'check';
  const h = document.createElement('h3');
  h.textContent = 'Check:';
  const q = document.createElement('p');
  q.textContent = check.question;
  box.append(h, q);
  check.choices.forEach((text, i) => {
    const b = document.createElement('button');
    b.id = `check-choice-${i}`;
    b.className = 'choice';
    b.textContent = text;
    b.addEventListener('click', () => send({ type: 'answer', choice: i }));
    box.appendChild(b);
  });
  const fb = document.createElement('p');
  fb.id = 'check-feedback';
  box.appendChild(fb);
  document.querySelector('main').appendChild(box);
}

function showTask(task) {
  lab.task = task || null;
  if (!task) return;
  let box = document.getElementById('task');
  if (!box) {
    box = document.createElement('section');
    box.id = 'task';
    box.className = 'check task';
    const h = document.createElement('h3');
    h.textContent = 'Try this:';
    const p = document.createElement('p');
    p.id = 'task-prompt';
    const r = document.createElement('p');
    r.id = 'task-result';
    box.append(h, p, r);
    const check = document.getElementById('check');
    const main = document.querySelector('main');
    if (check) main.insertBefore(box, check); else main.appendChild(box);
  }
  document.getElementById('task-prompt').textContent = task.prompt;
  const r = document.getElementById('task-result');
  r.textContent = task.result || 'The page is watching for it.';
  box.classList.toggle('done', Boolean(task.result));
}

function showFeedback(msg) {
  lab.feedback = msg;
  const fb = document.getElementById('check-feedback');
  if (!fb) return;
  fb.textContent = msg.message;
  fb.className = msg.correct ? 'right' : 'wrong';
  document.querySelectorAll('#check .choice').forEach((b, i) => {
    b.classList.toggle('picked-right', msg.correct && i === msg.choice);
    b.classList.toggle('picked-wrong', !msg.correct && i === msg.choice);
  });
}

// every control shows the server's value of its parameter, also right after the user changed it (the server may
// have refused the change, or replaced it: an estimator that cannot run in this world falls back to another); only
// a control in the middle of an edit (a slider being dragged, a number being typed) is left alone
const editing = new Set();
function showValues() {
  for (const [name, v] of Object.entries(lab.values)) {
    const input = document.getElementById(`ctl-${name}`);
    if (!input || editing.has(input)) continue;
    if (input.type === 'checkbox') input.checked = !!v; else input.value = v;
    const out = document.getElementById(`out-${name}`);
    if (out && paramsByName[name] && ['float', 'int'].includes(paramsByName[name].kind)) out.textContent = fmt(v);
  }
}

function applyState(msg) {
  lab.values = msg.values || {};
  lab.notices = msg.notices || [];
  showTask(msg.task);
  showValues();
  noticesEl.innerHTML = '';
  for (const n of lab.notices) {
    const d = document.createElement('div');
    d.className = 'notice';
    d.textContent = n;
    noticesEl.appendChild(d);
  }
  if (msg.bounds) { worldBounds = msg.bounds.slice(); view.setBounds(worldBounds); }
  // only the rows that apply to the current settings are shown
  const rows = new Set(msg.rows || scalarNames);
  lab.rows = Array.from(rows);
  for (const el of numbersEl.querySelectorAll('[data-row]')) el.hidden = !rows.has(el.dataset.row);
  // controls that change nothing under the current settings are greyed out
  lab.inactive = msg.inactive || [];
  for (const name of Object.keys(paramsByName)) {
    const input = document.getElementById(`ctl-${name}`);
    if (input) input.disabled = lab.inactive.includes(name);
  }
}

function onText(text) {
  const msg = JSON.parse(text);
  if (msg.type === 'hello') {
    lab.hello = msg;
    scalarNames = msg.scalars || [];
    buildNumbers(scalarNames, msg.labels);
    buildControls(msg.params || [], msg.actions || []);
    buildCheck(msg.check);
    for (const b of document.querySelectorAll('#check button')) b.disabled = false; // after a reconnect
    applyState(msg);
  } else if (msg.type === 'state') {
    if (!msg.pushed) lab.states += 1;  // replies to accepted commands (tests wait on it instead of sleeping)
    applyState(msg);
  } else if (msg.type === 'feedback') {
    showFeedback(msg);
  } else if (msg.type === 'error') {
    showValues(); // a refused change: the control goes back to the value the session kept
    lab.errors.push(msg.message);
    const d = document.createElement('div');
    d.className = 'error';
    d.textContent = msg.message;
    errorsEl.prepend(d);
    while (errorsEl.childElementCount > 3) errorsEl.lastChild.remove();
  }
}

function onFrame(buf) {
  const t0 = performance.now();
  const f = decodeFrame(buf);
  lab.decodeMs = performance.now() - t0;
  lab.frames += 1;
  lab.bytes += buf.byteLength;
  if (lab.recorded && lab.recorded.length < lab.record) lab.recorded.push(buf.slice(0)); // benchmark hook
  lab.seq = f.seq;
  latest = f;
  const s = f.sections;
  if (s.NUMS) {
    const c = {};
    scalarNames.forEach((n, i) => { c[n] = s.NUMS.data[i]; });
    lab.counters = c;
  }
  if (s.TPOS) lab.pose = Array.from(s.TPOS.data);
  if (s.EPOS) lab.estPose = Array.from(s.EPOS.data);
  lab.sections = Object.fromEntries(Object.entries(s).map(([k, v]) => [k, [v.rows, v.cols]]));
}

function connect() {
  const proto = location.protocol === 'https:' ? 'wss' : 'ws';
  const qs = new URLSearchParams();
  for (const k of ['seed', 'hz']) if (query.has(k)) qs.set(k, query.get(k));
  ws = new WebSocket(`${proto}://${location.host}/ws/${page}?${qs}`);
  ws.binaryType = 'arraybuffer';
  ws.onopen = () => { lab.connected = true; lab.openedAt = performance.now(); statusEl.textContent = BUILDING; };
  ws.onclose = () => { lab.connected = false; statusEl.textContent = 'disconnected from the lab server'; lost(); };
  ws.onmessage = (ev) => { if (typeof ev.data === 'string') onText(ev.data); else onFrame(ev.data); };
}

// the socket closed (the server stopped or restarted, or refused this page): say so where the controls are, grey the
// controls out (they cannot reach a session now), and offer a new connection, which starts a new session
function lost() {
  for (const el of document.querySelectorAll('#controls input, #controls select, #controls button, #check button')) {
    el.disabled = true;
  }
  if (document.getElementById('lost')) return;
  const box = document.createElement('div');
  box.id = 'lost';
  box.className = 'error';
  const text = document.createElement('span');
  text.textContent = 'The connection to the lab server closed: this page has stopped and its controls do nothing. ' +
    'If the server stopped, start it again (make run), then reconnect for a new session. ';
  const b = document.createElement('button');
  b.id = 'reconnect';
  b.textContent = 'reconnect';
  b.addEventListener('click', () => { box.remove(); lab.lost = null; lab.hello = null; connect(); });
  box.append(text, b);
  noticesEl.before(box);
  lab.lost = box.textContent;
}

// the numbers panel, at most 10 times a second (text that changes 60 times a second cannot be read, and every
// change re-lays out the page); only the values whose text changed are written
let numbersAt = -Infinity;
const numberEls = new Map();
function showNumbers(now) {
  if (now - numbersAt < 100) return;
  numbersAt = now;
  for (const [n, v] of Object.entries(lab.counters)) {
    let el = numberEls.get(n);
    if (!el || !el.isConnected) {
      el = numbersEl.querySelector(`[data-num="${n}"]`);
      numberEls.set(n, el);
    }
    const text = fmt(v);
    if (el && el.textContent !== text) el.textContent = text;
  }
}

function draw() {
  if (!latest || latest.seq === drawnSeq) return;
  const t0 = performance.now();
  const s = latest.sections;
  fitEstimate(s);
  view.base(s); // white, grid image, walls, true landmarks: redrawn only when they or the view change
  view.dots(s.SCAN, COLORS.scan, 2);
  view.segments(s.GEDG, COLORS.graphEdge, 1);
  view.circle(s.RNGE, COLORS.range);
  // the paths: a path's rows stay put while it grows (the server's power-of-two stride), its newest row moves; the
  // part drawn directly starts at the last cached row, so the two parts join
  view.cached('paths', [s.TPTH, s.GHST, s.EPTH], 1, (from, to) => {
    const f = from.map((v) => Math.max(v - 1, 0));
    view.path(s.TPTH, COLORS.truePath, 2, [], f[0], to[0]);
    view.path(s.GHST, COLORS.ghost, 1.5, [2, 3], f[1], to[1]);
    view.path(s.EPTH, COLORS.estPath, 2, [6, 4], f[2], to[2]);
  }, { append: true, live: 1 });
  if (s.OCOV) view.ellipses(s.OBSV, s.OCOV, COLORS.obsEllipse);
  view.rays(s.EPOS, s.OBSV, COLORS.obs);
  // the estimated landmarks and their ellipses: a graph back end moves them only when it optimises
  lab.ellipsesDrawn = view.cached('landmarks', [s.ELMK, s.ECOV], 1, (from, to) => {
    const n = view.ellipses(s.ELMK, s.ECOV, COLORS.ellipse, 2, 2, from[0], to[0]);
    view.dots(s.ELMK, COLORS.estLm, 5, null, from[0], to[0]);
    return n;
  }, { append: true });
  view.dots(s.GNOD, COLORS.graphNode, 3);
  view.dots(s.PART, COLORS.particle, 3, 3);
  view.matches(s.MTCH);
  view.dots(s.NEWO, COLORS.newObs, 6);
  view.dots(s.TCOR, COLORS.trueCorner, 9);
  view.crosses(s.FEAT, COLORS.feature, 5);
  if (s.PCOV && s.EPOS) view.ellipses(s.EPOS, s.PCOV, COLORS.ellipse, 3);
  if (lab.extraDraw) lab.extraDraw(view, s); // a page's own sections (e.g. warehouse.html)
  view.robot(s.TPOS, COLORS.robot);
  view.robot(s.EPOS, COLORS.estRobot, 0.35);
  if (heatCanvas) drawHeat(heatCanvas, s.HEAT);
  if (zoomCanvas) lab.zoom = drawParticleZoom(zoomCanvas, s.PART, s.TPOS);
  showNumbers(t0);
  drawnSeq = latest.seq;
  lab.drawn += 1;
  lab.drawMs = performance.now() - t0;
}

// frame-rate bookkeeping: frames drawn and received per second, over 1 s windows
let winStart = performance.now(), winDrawn = 0, winFrames = 0;
function loop() {
  draw();
  const now = performance.now();
  if (now - winStart >= 1000) {
    lab.fps = ((lab.drawn - winDrawn) * 1000) / (now - winStart);
    lab.recvFps = ((lab.frames - winFrames) * 1000) / (now - winStart);
    winStart = now; winDrawn = lab.drawn; winFrames = lab.frames;
    // the rates only once the session is there; before it the status says what the page waits for, and after a
    // disconnect it keeps saying so (0 frames/s would read as a stalled page)
    if (lab.connected && lab.hello === null) {
      statusEl.textContent = `${BUILDING} ${((now - lab.openedAt) / 1000).toFixed(0)} s`;
    } else if (lab.connected) {
      const p = lab.pose ? lab.pose.map((v) => v.toFixed(2)).join(', ') : '–';
      statusEl.textContent = `${lab.recvFps.toFixed(1)} frames/s received, ${lab.fps.toFixed(1)} drawn · ` +
        `pose (${p}) · ${(lab.bytes / Math.max(lab.frames, 1) / 1024).toFixed(1)} KiB/frame`;
    }
    lab.statusTicks += 1;
  }
  requestAnimationFrame(loop);
}

const DRIVE = new Set(['ArrowUp', 'ArrowDown', 'ArrowLeft', 'ArrowRight']);
const held = new Set(); // drive keys whose press the server got: their release is sent wherever the focus is then
window.addEventListener('keydown', (e) => {
  if (!DRIVE.has(e.key)) return;
  if (e.target && ['INPUT', 'SELECT'].includes(e.target.tagName)) return;
  e.preventDefault();
  if (!e.repeat) { held.add(e.key); send({ type: 'key', key: e.key, down: true }); }
});
window.addEventListener('keyup', (e) => {
  if (!DRIVE.has(e.key)) return;
  const inControl = e.target && ['INPUT', 'SELECT'].includes(e.target.tagName);
  if (!held.delete(e.key) && inControl) return;
  if (!inControl) e.preventDefault();
  send({ type: 'key', key: e.key, down: false });
});
window.addEventListener('blur', () => {
  held.clear();
  for (const k of DRIVE) send({ type: 'key', key: k, down: false });
});

connect();
requestAnimationFrame(loop);
