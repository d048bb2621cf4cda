// What every page of the station shares: $ and esc, the token, and the header with the engine's state,
// STOP and E-STOP. A person may be strapped to the rig whichever page is open (the gap diagnosis runs
// its protocol on the connected rig), so stopping it never depends on the page: E-STOP answers from any
// state and needs no token.
'use strict';

const $ = id => document.getElementById(id);
// text put into HTML: every character that could open a tag or end an attribute, escaped (null shows as '')
const esc = v => String(v ?? '').replace(/[&<>"']/g, c => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;'})[c]);

// a chart's legend entry: its key (■, —, ┄┄, …) drawn in the series' colour, its words in the page's. A
// colour that reads as a line does not always read as small text: the words keep WCAG 1.4.3's 4.5:1
// (the tab10 green of P_a reached 3.4 : 1 as text), and a screen reader reads the words, not the key
function legendItem(key, colour, text) {
  const k = Object.assign(document.createElement('span'), {className: 'key', textContent: key});
  k.style.color = colour;
  k.setAttribute('aria-hidden', 'true');
  const item = document.createElement('span');
  item.append(k, ` ${text}`);
  return item;
}

// the token lives in this tab only (sessionStorage), never in the page's address or a cookie
function authHeaders() {
  const t = sessionStorage.getItem('cwrr-token');
  return t ? {'Authorization': `Bearer ${t}`} : {};
}

// when an E-STOP press went unconfirmed [ms since the page loaded]: its warning stays in the header for
// 5 s, not overwritten by the next poll's state, unless that state shows the fault latched after all
let estopUnconfirmedAt = -Infinity;

// the engine's state in the header; STOP where the engine has something to stop (E-STOP is never disabled)
function showEngineState(st) {
  $('stop').disabled = !st.allowed.includes('stop');
  if (st.state !== 'fault' && performance.now() - estopUnconfirmedAt < 5000) return;
  const s = $('state');
  s.textContent = st.state;
  s.className = st.state;
  // what latched a fault, on the badge itself (the diagnosis page has no other place to say it)
  s.title = st.state === 'fault' ? `${st.fault || 'a fault'}: latched until cleared on the Station page` : '';
}

// why the header has no state to show (no answer, no sign-in), unless an E-STOP warning is being held
function showNoState(text) {
  if (performance.now() - estopUnconfirmedAt >= 5000) $('state').textContent = text;
}

// press E-STOP; `shown` draws the status the station answers with (the page's own renderer, if it has one)
async function pressEstop(shown = showEngineState) {
  const r = await fetch('/api/engine/estop', {method: 'POST', headers: authHeaders()}).catch(() => null);
  if (r && r.ok) { shown(await r.json()); return; }
  const why = r ? ((await r.json().catch(() => ({}))).detail || r.statusText) : 'the station does not answer';
  estopUnconfirmedAt = performance.now();
  $('state').textContent = 'E-STOP NOT CONFIRMED: ' + why;
  $('state').className = 'fault';
}

// the last state watchEngine's poll read, and when that request was sent [ms since the page loaded]:
// what else on the page follows the engine reads it here rather than polling the station a second time
let engineSeen = {state: null, sent: -Infinity};

// a page without its own engine poll: keep the header's state current (one request at a time, each
// given up after 10 s: a half-open connection must not freeze the state shown next to E-STOP)
function watchEngine(periodMs = 1000) {
  const stop = $('stop');
  stop.addEventListener('click', async () => {
    stop.disabled = true;
    const r = await fetch('/api/engine/stop', {method: 'POST', headers: authHeaders()}).catch(() => null);
    if (r && r.ok) showEngineState(await r.json());
  });
  $('estop').addEventListener('click', () => pressEstop());
  const tick = async () => {
    const t = performance.now();
    try {
      const r = await fetch('/api/engine', {headers: authHeaders(), signal: AbortSignal.timeout(10000)});
      if (r.ok) { const st = await r.json(); engineSeen = {state: st, sent: t}; showEngineState(st); }
      else showNoState(r.status === 401 || r.status === 403 ? 'sign in' : 'station error');
    } catch (e) {
      showNoState('server not reachable');
    } finally {
      setTimeout(tick, Math.max(0, periodMs - (performance.now() - t)));
    }
  };
  tick();
}

// a chart's gridlines at round values (steps of 1, 2, 2.5 or 5 × 10^k, about n of them from lo to hi),
// and the digits that print them
function niceTicks(lo, hi, n = 4) {
  const raw = (hi - lo) / n;
  if (!(raw > 0) || !isFinite(raw)) return {ticks: [lo], digits: 2};
  const mag = 10 ** Math.floor(Math.log10(raw));
  const mult = [1, 2, 2.5, 5, 10].find(m => m * mag >= raw * (1 - 1e-9));
  const step = mult * mag;
  const digits = Math.max(0, -Math.floor(Math.log10(step) + 1e-9) + (mult === 2.5 ? 1 : 0));
  const ticks = [];
  for (let k = Math.ceil(lo / step - 1e-9); k * step <= hi + step * 1e-9; k++) ticks.push(k * step);
  return {ticks, digits};
}
const tickLabel = (v, digits) => (Math.abs(v) < 1e-12 ? 0 : v).toFixed(digits);
