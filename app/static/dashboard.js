// The station dashboard (index.html): the engine's state and actions, the exercise, identification and
// tuning forms, the live charts, the last result and the run history. What every page shares (the
// header's E-STOP, the token, $ and esc) is in station.js, loaded first.
const METRICS = {mae: 'MAE [N·m]', iae: 'IAE [N·m·s]', itae: 'ITAE [N·m·s²]', evar: 'e_var [N²·m²]',
                 rmse: 'RMSE [N·m]', maxae: 'Max AE [N·m]'};
let status = {state: 'disconnected', allowed: []};
let identReady = false;
let identRig = 'rotary';
let identCyl = 'C3';  // the linear form suggests this cylinder's catalogue geometry

// a refusal names the field as the form labels it, not as the API spells it
const FIELD_NAMES = {target_nm: 'Target torque', person: 'Person id', session_id: 'Therapy session',
                     notes: 'Notes', gains_id: 'Pressure-loop gains', workout_id: 'Exercise shape',
                     bandwidth_rad_s: 'Target bandwidth', phase_margin_deg: 'Phase margin', pw_bar: 'Working pressure'};
function fieldName(f) { return FIELD_NAMES[f] || f; }

async function api(method, path, body) {
  // a read that never answers (a half-open connection) must not stall the poll that made it
  let r;
  try {
    r = await fetch(path, {method, headers: {'Content-Type': 'application/json', ...authHeaders()},
                           body: body === undefined ? undefined : JSON.stringify(body),
                           signal: method === 'GET' ? AbortSignal.timeout(10000) : undefined});
  } catch (e) {
    // the browser's own words ("Failed to fetch", "NetworkError when…") say nothing to a therapist
    const err = new Error(e.name === 'TimeoutError' ? 'the station did not answer within 10 s'
                                                    : 'the station did not answer (is it running?)');
    err.status = 0;
    throw err;
  }
  const data = await r.json().catch(() => ({}));
  if (r.status === 401) { $('signin').hidden = false; }
  if (!r.ok) {
    const d = data.detail;
    const msg = Array.isArray(d) ? d.map(e => `${fieldName(e.loc[e.loc.length - 1])}: ${e.msg}`).join('; ') : (d || r.statusText);
    const err = new Error(msg); err.status = r.status;
    throw err;
  }
  return data;
}

function say(id, text, ok) { const el = $(id); el.textContent = text; el.className = 'msg ' + (ok ? 'ok' : 'bad'); delete el.dataset.ready; }

function render(st) {
  status = st;
  showEngineState(st);
  const RIG_NAMES = {rotary: 'forearm robot', linear: 'linear cylinder', cpr: 'valve test set-up with cylinder'};
  const rigName = st.rig ? RIG_NAMES[st.rig.kind] + (st.rig.kind === 'rotary' ? '' : ` ${st.rig.cylinder}`) : '';
  $('backend').textContent = st.backend ? `(${st.backend === 'sim' ? 'simulated' : st.backend} ${rigName})` : '';
  $('rig').disabled = st.state !== 'disconnected';
  if (st.rig && st.state !== 'disconnected') {  // the rig connected, also when a script or another tab chose it
    const v = st.rig.kind === 'rotary' ? 'rotary' : `${st.rig.kind}:${st.rig.cylinder}`;
    if ([...$('rig').options].some(o => o.value === v)) $('rig').value = v;
  }
  const rigKind = st.rig ? st.rig.kind : $('rig').value.split(':')[0];
  const formRig = rigKind === 'cpr' ? identRig : rigKind;  // the friction form stays as it was on the valve set-up
  const rigCyl = st.rig ? st.rig.cylinder : ($('rig').value.split(':')[1] || 'C3');
  const formCyl = rigKind === 'cpr' ? identCyl : rigCyl;
  // another rig, or another cylinder on the linear one, starts the form over: what was typed was for the other
  if (formRig !== identRig || (formRig === 'linear' && formCyl !== identCyl)) {
    identRig = formRig; identCyl = formCyl; $('ident-fields').innerHTML = ''; checkForm();
  } else identCyl = formCyl;
  $('dcv-box').hidden = rigKind !== 'cpr';
  $('pid-box').hidden = rigKind !== 'rotary';
  // the linear cylinder's load cell measures a force, and nothing there follows a torque target
  const rotary = rigKind === 'rotary';
  $('live-force').textContent = rotary ? 'interaction torque [N·m]' : 'cylinder force [N]';
  $('live-target').hidden = !rotary;
  const sm = $('start-msg');
  if (!rotary && st.state !== 'disconnected') {
    sm.className = 'msg'; sm.textContent = 'Exercises run on the forearm robot: disconnect, choose it under Rig and connect.';
    sm.dataset.rig = '1';
  } else if (sm.dataset.rig) { sm.textContent = ''; delete sm.dataset.rig; }
  // the thesis GUI's words once the form is complete ask to connect; say so when the station already is
  const im = $('ident-msg');
  if (im.dataset.ready) {
    im.textContent = im.dataset.ready + (st.state === 'idle' && rigKind !== 'cpr'
      ? ' The station is connected: Run identification starts the experiments.' : '');
  }
  document.querySelectorAll('[data-action]').forEach(b => {
    let ok = st.allowed.includes(b.dataset.action);
    if (b.id === 'estimate') ok = ok && identReady && rigKind !== 'cpr';
    if (b.dataset.rig) ok = ok && st.rig && st.rig.kind === b.dataset.rig;
    b.disabled = !ok || (b.hasAttribute('data-admin') && !isAdmin());
  });
  document.querySelectorAll('.admin-note').forEach(n => {
    n.hidden = isAdmin();
    n.textContent = signedIn.role === 'therapist' ? 'Needs the admin role: this tab is signed in as a therapist.'
                                                  : 'Needs the admin role: sign in with an admin token.';
  });
  // sensor calibration exists for backends with a scaling (modbus, quanser), not for the simulator
  $('cal-box').hidden = !st.calibration;
  if (st.calibration) {
    document.querySelectorAll('.cal').forEach(b => {
      b.disabled = st.state !== 'idle' || !isAdmin();
      b.textContent = b.textContent.replace(/ \(.*\)$/, '') + ` (${st.calibration[b.dataset.cal] || 'never'})`;
    });
  }
  const sf = st.safety || {};
  const onRig = st.state !== 'disconnected' && st.rig ? st.rig : null;
  setGauge(onRig ? sf.limits : null, onRig);
  $('engine-msg').textContent = st.fault ? 'Fault: ' + st.fault + (sf.fault ? ` [${sf.fault.code}] — the rig is vented; clear the fault to reconnect` : '')
    : (sf.no_action ? 'Soft range-of-motion limit: holding equal pressures' : '');
  const p = st.progress;
  $('progress-box').hidden = !p;
  if (p) {
    $('progress').value = p.fraction || 0;
    const PHASES = {pressurising: 'filling both chambers', exercising: 'exercising',
                    releasing: 'ending: both chambers emptying together'};
    $('progress-msg').textContent = p.kind === 'workout' ? `Exercise: ${PHASES[p.phase] || p.phase}` : (p.message || p.phase);
  }
  if (st.last_run && JSON.stringify(st.last_run) !== render.lastShown) {
    render.lastShown = JSON.stringify(st.last_run);
    shownRun = null;  // a run that just ended takes the panel back from one picked in the history
    showLast(st.last_run); loadRuns(); showRunNotes(st.last_run.run_id);
    // "Exercise started" under the Start button had stayed there after the exercise ended
    const lr = st.last_run;
    if (sm.dataset.run === String(lr.run_id)) {
      const ENDED = {complete: 'ran to its end', stopped: 'was stopped', fault: 'ended in a fault', interrupted: 'was interrupted'};
      say('start-msg', `Exercise ${lr.run_id} ${ENDED[lr.status] || lr.status}: its result is under Last result.`,
          lr.status === 'complete' || lr.status === 'stopped');
      delete sm.dataset.run;
    }
    if ($('session').value) loadSessions($('session').value);  // its run count
  } else if (!st.last_run && render.lastShown === undefined) {
    // a station restarted since its last run keeps none in memory, and the panel had said "No run
    // finished yet" over a history of runs: the newest stored run that has ended is shown, as if picked
    // there (a page opened during the restarted station's first run had shown that run as "running")
    render.lastShown = null;
    api('GET', '/api/runs?limit=2&with_result=false')
      .then(rs => {
        const ended = rs.find(r => r.status !== 'running');
        if (ended && render.lastShown === null && shownRun === null) return showRun(ended.id);
      })
      .catch(() => {});  // the history says what is wrong with the store
  }
}

// the charts only some kinds of result draw (a friction curve, a valve map, a Bode chart), hidden until one does
function hideResultCharts() {
  ['c-friction', 'friction-legend', 'c-cpr', 'cpr-legend', 'c-bode', 'bode-legend'].forEach(id => { $(id).hidden = true; });
}
// what an exercise was, as the history names it: scenario · controller · target
const exerciseWhat = spec => `${spec.scenario} · ${spec.controller} · ${spec.target_nm} N·m`;
// an angle in the words of the exercise [deg, positive: pronation]
function angleWords(v) {
  const r = Math.round(Math.abs(v));
  return r === 0 ? 'neutral (0°)' : `${r}° ${v > 0 ? 'pronation' : 'supination'}`;
}
// the lowest and highest angle an exercise reached, [lo, hi] [deg]
function rangeWords([lo, hi]) {
  return `from ${angleWords(lo)} to ${angleWords(hi)} (${Math.round(hi - lo)}° in all)`;
}
function showLast(lr) {
  hideResultCharts();
  const r = lr.result || {};
  // the station's last run carries its number and metrics only: what it was comes with the stored run
  drawTrace(lr.run_id, lr.run).then(run => {
    const what = $(`last-what-${lr.run_id}`);
    if (what && run && run.kind === 'workout' && run.spec) {
      what.textContent = ` (${exerciseWhat(run.spec)}${run.person ? ', ' + run.person : ''})`;
    }
    // what the station noticed about the run (a chamber's pressure loop chattering), under its metrics
    const warn = $(`last-warn-${lr.run_id}`), ws = run && run.result && run.result.warnings;
    if (warn && Array.isArray(ws) && ws.length) { warn.textContent = ws.join(' '); warn.hidden = false; }
    // how far the arm went, beside how well the torque was tracked
    const rng = $(`last-range-${lr.run_id}`), ar = run && run.result && run.result.angle_range_deg;
    if (rng && Array.isArray(ar) && ar.length === 2) { rng.textContent = `Range of motion reached: ${rangeWords(ar)}.`; rng.hidden = false; }
    if (run && run.kind === 'workout' && lr.metrics) drawComparison(lr.run_id);
  });
  if (lr.metrics) {
    const part = r.partial ? ` — scored over the ${(r.window_s[1] - r.window_s[0]).toFixed(1)} s reached before the stop` : '';
    $('last').innerHTML = `<p>Exercise ${esc(lr.run_id)}<span id="last-what-${esc(lr.run_id)}"></span>: ${esc(lr.status)}${esc(part)}</p><table id="metrics">` +
      Object.entries(METRICS).map(([k, l]) => `<tr><td>${l}</td><td>${fmt(lr.metrics[k], 4)}</td></tr>`).join('') +  // null: a metric the run could not give
      `</table><p id="last-range-${esc(lr.run_id)}" hidden></p><p id="last-warn-${esc(lr.run_id)}" class="msg bad" hidden></p>` +
      `<div id="last-compare-${esc(lr.run_id)}" class="compare" hidden></div>`;
  } else if (r.parameters && ('filling' in r.parameters || 'exhausting' in r.parameters)) {
    showValve(lr);
  } else if (r.parameters && 'ki' in r.parameters) {
    showTuning(lr);
  } else if (r.parameters) {
    showFriction(lr);
  } else if (r.logs) {  // the diagnosis protocol: its experiments' logs, to diagnose on the gap-diagnosis page
    const ids = (r.run_ids || []).filter(Number.isInteger);
    $('last').innerHTML = esc(`Diagnosis protocol ${lr.run_id}: ${lr.status} — ${r.logs.length} experiment log(s), ` +
      `runs ${ids.join(', ') || 'none'}` + (r.error ? ` (${r.error})` : '')) +
      (ids.length >= 2 ? ` — <a id="diagnose-runs" href="/static/diagnosis.html?runs=${ids.join(',')}">diagnose them</a>` : '');
  } else {
    $('last').textContent = `Run ${lr.run_id}: ${lr.status}` + (r.note ? ` (${r.note})` : '') + (r.error ? ` (${r.error})` : '');
  }
}

// The exercise beside each other controller's latest complete run on the same scenario, target and person,
// as the thesis's radar charts set them (Fig 4.26): each axis scaled by its largest value among them, so
// the worst touches the rim; every metric is an error, so the smaller shape is the better controller.
const CONTROLLERS = {default: ['Default', '#d62728', '7 4'], pid: ['Cascade PID', '#1f77b4', '2 3'],
                     fuzzy: ['Cascade fuzzy adaptive PID', '#2ca02c', '']};
async function drawComparison(id) {
  let c;
  try { c = await api('GET', `/api/runs/${id}/comparison`); } catch (e) { return; }  // nothing to compare: no chart
  const box = $(`last-compare-${id}`);
  if (!box) return;  // another result was shown meanwhile
  const name = k => (CONTROLLERS[k] || [k])[0];
  const what = `${c.scenario} at ${c.target_nm} N·m${c.person ? ' for ' + c.person : ''}`;
  const missing = c.missing.length ? `<p class="msg">No complete ${esc(what)} yet with ${esc(c.missing.map(name).join(' or '))}: ` +
    'such an exercise, run to its end, is drawn here beside this one.</p>' : '';
  box.hidden = false;
  if (c.runs.length < 2) { box.innerHTML = missing; return; }
  const keys = Object.keys(METRICS).filter(k => k in c.scale);
  const W = 330, H = 266 + 15 * c.runs.length, cx = W / 2, cy = 132, R = 92;
  const pt = (k, r) => { const a = -Math.PI / 2 + 2 * Math.PI * k / keys.length;  // the first axis up, clockwise
    return [cx + r * Math.cos(a), cy + r * Math.sin(a)]; };
  const ring = f => keys.map((_, k) => pt(k, R * f).map(v => v.toFixed(1)).join(',')).join(' ');
  let svg = [0.25, 0.5, 0.75, 1].map(f => `<polygon points="${ring(f)}" fill="none" stroke="#d5dbe3"/>`).join('');
  keys.forEach((m, k) => {
    const [x, y] = pt(k, R), [lx, ly] = pt(k, R + 16);
    const anchor = Math.abs(lx - cx) < 5 ? 'middle' : lx > cx ? 'start' : 'end';
    svg += `<line x1="${cx}" y1="${cy}" x2="${x.toFixed(1)}" y2="${y.toFixed(1)}" stroke="#d5dbe3"/>` +
      `<text x="${lx.toFixed(1)}" y="${(ly - 5).toFixed(1)}" font-size="11" text-anchor="${anchor}">${esc(METRICS[m].replace(/ \[.*\]$/, ''))}` +
      `<tspan x="${lx.toFixed(1)}" dy="12" fill="#5b6776" font-size="10">max ${fmt(c.scale[m])}</tspan></text>`;
  });
  // a legend inside the drawing too, so that the saved chart stands on its own
  c.runs.forEach((r, k) => {
    const [nm, col, dash] = CONTROLLERS[r.controller] || [r.controller, '#333', ''], y = 268 + 15 * k;
    svg += `<line x1="20" y1="${y}" x2="44" y2="${y}" stroke="${col}" stroke-width="2" stroke-dasharray="${dash}"/>` +
      `<text x="50" y="${y + 4}" font-size="11">${esc(nm)}, run ${r.run_id}${r.run_id === c.run_id ? ' (this one)' : ''}</text>`;
  });
  [...c.runs].reverse().forEach(r => {  // the exercise itself drawn last, on top
    const [nm, col, dash] = CONTROLLERS[r.controller] || [r.controller, '#333', ''];
    const pts = keys.map((m, k) => pt(k, R * r.metrics[m] / c.scale[m]).map(v => v.toFixed(1)).join(',')).join(' ');
    svg += `<polygon points="${pts}" fill="${col}" fill-opacity="0.08" stroke="${col}" stroke-width="2" stroke-dasharray="${dash}" ` +
      `data-controller="${esc(r.controller)}" data-run="${r.run_id}"><title>${esc(nm)}, run ${r.run_id}</title></polygon>`;
  });
  // each column's head is the chart's legend: the controller's line as drawn, its name (a link to that run)
  const head = c.runs.map(r => {
    const [nm, col, dash] = CONTROLLERS[r.controller] || [r.controller, '#333', ''];
    return `<th><svg width="24" height="8" aria-hidden="true"><line x1="0" y1="4" x2="24" y2="4" stroke="${col}" stroke-width="2" ` +
      `stroke-dasharray="${dash}"/></svg> <a href="#" data-show-run="${r.run_id}">${esc(nm)}</a><br>` +
      `<small class="muted">run ${r.run_id}${r.run_id === c.run_id ? ' (this one)' : ''}</small></th>`;
  }).join('');
  const rows = keys.map(m => `<tr><td>${METRICS[m]}</td>` + c.runs.map(r => {
    const v = fmt(r.metrics[m], 3);
    return `<td>${c.best[m] === r.controller ? `<b>${v}</b>` : v}</td>`;
  }).join('') + '</tr>').join('');
  box.innerHTML = `<p style="margin-bottom:.2rem">Compared with the other controllers: ${esc(what)}, each one's latest complete exercise ` +
    '(smaller is better; the best of each metric in bold).</p>' +
    '<div style="display:flex;flex-wrap:wrap;gap:1rem;align-items:flex-start">' +
    `<svg width="${W}" height="${H}" role="img" aria-label="radar chart comparing the controllers" xmlns="http://www.w3.org/2000/svg" ` +
    `font-family="system-ui, sans-serif"><title>${esc(what)}: ${esc(c.runs.map(r => `${name(r.controller)} (run ${r.run_id})`).join(', '))}</title>${svg}</svg>` +
    `<div style="flex:1 1 16rem"><table id="compare-table"><tr><th>metric</th>${head}</tr>${rows}</table>` +
    '<p class="msg">Each axis of the chart is scaled by its largest value among these runs, which touches the rim. ' +
    `<a href="#" data-svg="${c.run_id}">Save the chart (SVG)</a></p></div></div>` + missing;
}
// a run named in a comparison: its own result, as a click on it in the history shows it
$('last').addEventListener('click', ev => {
  // the radar as a file for a report: the drawing itself, with the legend drawn inside it
  const save = ev.target.closest('a[data-svg]');
  if (save) {
    ev.preventDefault();
    const svg = save.closest('.compare').querySelector('svg[role=img]');
    const url = URL.createObjectURL(new Blob(['<?xml version="1.0" encoding="UTF-8"?>\n' + svg.outerHTML], {type: 'image/svg+xml'}));
    const tmp = document.createElement('a'); tmp.href = url; tmp.download = `comparison-run-${save.dataset.svg}.svg`;
    tmp.click(); setTimeout(() => URL.revokeObjectURL(url), 1000);
    return;
  }
  const a = ev.target.closest('a[data-show-run]');
  if (!a) return;
  ev.preventDefault();
  showRun(a.dataset.showRun).catch(e => { $('hist-msg').className = 'msg bad'; $('hist-msg').textContent = `run ${a.dataset.showRun}: ${e.message}`; });
});

// An exercise's whole trace, once it ended: the live chart moves on with the idle rig, and a run picked
// in the history is long gone from it. The torque against its target, the scored window tinted.
let traceFor = null;
// run: the stored run when the caller has it (a run picked in the history), else it is fetched;
// resolves to the stored run (null when there is none or it could not be read)
async function drawTrace(id, run = null) {
  traceFor = id;
  const c = $('c-trace'), cp = $('c-trace-press');
  c.hidden = $('trace-legend').hidden = cp.hidden = $('trace-press-legend').hidden = true;
  if (id === null || id === undefined) return null;
  try {
    run = run || await api('GET', `/api/runs/${id}`);
  } catch (e) { return null; }  // the result above still shows; the state poll reports an unreachable server
  try {
    if (run.kind !== 'workout' || !run.has_series) return run;
    const s = await api('GET', `/api/runs/${id}/series?max_rows=1800`);
    const it = s.columns.indexOf('t'), iq = s.columns.indexOf('torque');
    if (traceFor !== id || s.rows.length < 2) return run;  // another run was picked meanwhile
    const tgt = run.spec && typeof run.spec.target_nm === 'number' ? run.spec.target_nm : null;
    // the scored window counts from the program's start, which the result puts on the log's clock;
    // the target holds from there on, as on the live chart (before it the chambers are pressurised)
    const res = run.result || {};
    const from = typeof res.program_start_s === 'number' ? res.program_start_s : -Infinity;
    const rows = s.rows.map(r => [r[it], r[iq], r[it] >= from ? tgt : null]);
    c.hidden = $('trace-legend').hidden = false;
    const shade = res.window_s && typeof res.program_start_s === 'number'
      ? res.window_s.map(x => x + res.program_start_s) : null;
    draw(c, [[1, '#1f77b4'], [2, '#d62728', true]], -0.2, 0.2, rows, shade);
    c.dataset.window = shade ? shade.map(x => x.toFixed(3)).join(',') : '';
    c.dataset.run = id; c.dataset.samples = rows.length;
    // the chambers beside what their regulators were told to hold: a PRV's set pressure is its
    // command in volts read as bar gauge (Eq 3.7), so the log's own atmosphere puts it in bar abs
    const col = ['p_a', 'p_b', 'z_a', 'z_b'].map(n => s.columns.indexOf(n));
    if (col.some(i => i < 0)) return run;
    const atm = s.meta && typeof s.meta.p_atm_bar === 'number' ? s.meta.p_atm_bar : null;
    const set = (r, i) => atm === null ? null : r[i] + atm;
    const prow = s.rows.map(r => [r[it], r[col[0]], r[col[1]], set(r, col[2]), set(r, col[3])]);
    cp.hidden = $('trace-press-legend').hidden = false;
    draw(cp, [[1, '#2ca02c'], [3, '#2ca02c', true], [2, '#9467bd'], [4, '#9467bd', true]], 1, 1.2, prow, shade);
    cp.dataset.run = id; cp.dataset.samples = prow.length; cp.dataset.atm = atm === null ? '' : String(atm);
  } catch (e) { /* the result above still shows; the state poll reports an unreachable server */ }
  return run;
}

// optimiser results sit on a bound as 1e-18 rather than 0: show them as 0
const fmt = (v, n = 3) => (v === null || v === undefined || !isFinite(v)) ? '–' : Math.abs(v) < 1e-12 ? '0' : Number(v).toPrecision(n);

function showValve(lr) {
  const r = lr.result;
  const modes = ['filling', 'exhausting'].filter(m => r.parameters[m]);
  let html = `<p>Valve identification ${esc(lr.run_id)}: ${esc(lr.status)} — ${r.tests.cpr} mapping and ${r.tests.validation} validation experiments</p>`;
  modes.forEach(m => {
    const rows = r.parameters[m].table_4_1;
    html += `<p><b>${m === 'filling' ? 'Filling' : 'Exhausting'}</b> at the fit supply pressure (Table 4.1 form)</p>` +
      `<table class="dcv-table"><tr><th>u [V]</th><th>a [-]</th><th>ε [-]</th><th title="the new model's flow gain (module app.engine.ident.dcv)">g [kg/s·(J/kg)·Pa^−ε]</th><th>R²</th></tr>` +
      rows.map(q => `<tr><td>${fmt(q.u, 2)}</td><td>${fmt(q.a)}</td><td>${fmt(q.eps)}</td><td>${fmt(q.g)}</td><td>${fmt(q.r2)}</td></tr>`).join('') +
      '</table>';
  });
  if (r.validation_mape_pct) {
    const names = {new: 'New model (Eq 3.10–3.11)', standard: 'Standard (ISO 6358)', improved: 'Improved', bobrow: 'Bobrow–McDonell'};
    html += '<p><b>Validation</b>: mean error of predicted chamber pressure</p><table id="dcv-validation"><tr><th>Model</th><th>error [%]</th></tr>' +
      Object.entries(r.validation_mape_pct).map(([k, v]) => `<tr><td>${names[k] || esc(k)}</td><td>${fmt(v)}</td></tr>`).join('') + '</table>';
  }
  $('last').innerHTML = html;
  drawCpr(Object.fromEntries(modes.map(m => [m, r.parameters[m]])));
}

// The critical-pressure-ratio map (thesis 3.2.3, Figures 4.1–4.2): a against the signal, a line per
// supply pressure, filling solid and exhausting dashed; where a < 1 the valve throttles
const PS_COLORS = ['#1f77b4', '#ff7f0e', '#2ca02c', '#d62728', '#9467bd', '#8c564b', '#e377c2', '#7f7f7f'];
function drawCpr(maps) {
  const c = $('c-cpr'), modes = Object.keys(maps).filter(m => (maps[m].u_cpr || []).length);
  c.hidden = $('cpr-legend').hidden = !modes.length;
  if (!modes.length) return;
  const {ctx, W, H} = fitCanvas(c);
  const us = modes.flatMap(m => maps[m].u_cpr), ps = [...new Set(modes.flatMap(m => maps[m].ps_cpr))].sort((a, b) => a - b);
  const as = modes.flatMap(m => maps[m].a.flat()).filter(Number.isFinite);
  const u0 = Math.min(...us), u1 = Math.max(...us), span = Math.max(u1 - u0, 0.1);
  const lo = Math.min(0, ...as), hi = Math.max(1.05, ...as);
  const L = 46, R = 10, T = 18, B = 32;
  const X = u => L + (W - L - R) * (u - u0 + 0.03 * span) / (1.06 * span), Y = a => H - B - (H - B - T) * (a - lo) / (hi - lo);
  ctx.font = '11px sans-serif'; ctx.lineWidth = 1; ctx.strokeStyle = '#e3e6ea'; ctx.fillStyle = '#555';
  const yt = niceTicks(lo, hi, 4), xt = niceTicks(u0, u1, 6);
  gridY(ctx, yt, Y, L, W - R); gridX(ctx, xt, X, T, H - B);
  ctx.textAlign = 'left'; ctx.fillText('critical pressure ratio a [-]', 4, 11);
  ctx.textAlign = 'right'; ctx.fillText('valve signal u [V]', W - R, H - 3); ctx.textAlign = 'left';
  let drawn = 0;
  modes.forEach(m => {
    const mp = maps[m];
    mp.ps_cpr.forEach((p, j) => {
      const color = PS_COLORS[ps.indexOf(p) % PS_COLORS.length];
      const q = mp.u_cpr.map((u, i) => [u, mp.a[i][j]]).filter(([, a]) => Number.isFinite(a));
      ctx.strokeStyle = ctx.fillStyle = color; ctx.lineWidth = 1.6; ctx.setLineDash(m === 'filling' ? [] : [6, 4]);
      ctx.beginPath(); q.forEach(([u, a], k) => k ? ctx.lineTo(X(u), Y(a)) : ctx.moveTo(X(u), Y(a))); ctx.stroke();
      ctx.setLineDash([]); q.forEach(([u, a]) => { ctx.beginPath(); ctx.arc(X(u), Y(a), 2.5, 0, 6.3); ctx.fill(); });
      drawn += q.length;
    });
  });
  c.dataset.points = drawn;
  $('cpr-legend').replaceChildren(...ps.map((p, k) => legendItem('■', PS_COLORS[k % PS_COLORS.length], `P_s = ${fmt(p, 3)} bar`)),
    legendItem('—', 'inherit', 'filling'), legendItem('┄┄', 'inherit', 'exhausting'));
}

let lastTuning = null;
function showTuning(lr) {
  const r = lr.result, p = r.parameters;
  lastTuning = r.gains_fields;
  const rows = [['Tuned here', p, {crossover_rad_s: p.crossover_rad_s, phase_margin_deg: p.phase_margin_deg}]]
    .concat(Object.entries(r.thesis).map(([k, g]) => [k, g, r.thesis_margins[k]]));
  $('last').innerHTML = `<p>Pressure-loop tuning ${esc(lr.run_id)}: ${esc(lr.status)}</p>` +
    '<table id="pid-result"><tr><th></th><th>K_p [-]</th><th>K_i [1/s]</th><th>K_d [s]</th><th>crossover [rad/s]</th><th>phase margin [°]</th></tr>' +
    rows.map(([l, g, m]) => `<tr><td>${esc(l)}</td><td>${fmt(g.kp)}</td><td>${fmt(g.ki)}</td><td>${fmt(g.kd)}</td><td>${fmt(m.crossover_rad_s)}</td><td>${fmt(m.phase_margin_deg)}</td></tr>`).join('') +
    '</table>' + (p.note ? `<p class="msg">${esc(p.note)}</p>` : '') +
    `<button id="save-gains" type="button" ${isAdmin() ? '' : 'disabled title="Needs the admin role"'}>` +
    'Save as a gain set (the other regulator keeps Eq 3.26)</button>';
  if (r.loops && r.frf) drawBode(r.frf, r.loops, p.crossover_rad_s);
  $('save-gains').addEventListener('click', async () => {
    const values = {kp_a: 0.45, ki_a: 2.034, kd_a: 0.0098, kp_b: 0.55, ki_b: 2.042, kd_b: 0.0107, ...lastTuning};
    try {
      const s = await api('POST', '/api/params', {kind: 'gains', name: `tuned run ${lr.run_id}`, values});
      say('pid-msg', `Saved as gain set ${s.id}; choose it under Exercise.`, true); loadSets();
    } catch (e) { say('pid-msg', e.message, false); }
  });
}

// The tuning's Bode chart: the plant's response measured at the test frequencies (dots; coherence in
// the legend) and the open loop C·G of each gain set over that band, with 0 dB and −180° marked, so that
// where each crosses over and what margin it keeps can be read, as the table states them
const LOOP_COLORS = {'Tuned here': '#1f77b4', 'thesis autotuner': '#ff7f0e', 'thesis Eq 3.26': '#7f7f7f'};
function drawBode(frf, loops, wcTuned) {
  const c = $('c-bode'); c.hidden = $('bode-legend').hidden = false;
  const {ctx, W, H} = fitCanvas(c);
  const names = Object.keys(loops);
  const ws = frf.w_rad_s.concat(...names.map(k => loops[k].w_rad_s));
  const lw0 = Math.log10(Math.min(...ws)), lw1 = Math.log10(Math.max(...ws));
  const L = 46, R = 10, gap = 26, B = 30, T = 16, ph = (H - T - B - gap) / 2;
  const X = w => L + (W - L - R) * (Math.log10(w) - lw0) / Math.max(lw1 - lw0, 1e-9);
  // 1-2-5 marks of ω over the band
  const xt = [];
  for (let e = Math.floor(lw0); e <= Math.ceil(lw1); e++) [1, 2, 5].forEach(m => {
    const w = m * 10 ** e; if (Math.log10(w) >= lw0 - 1e-9 && Math.log10(w) <= lw1 + 1e-9) xt.push(w); });
  const panel = (top, key, plant, mark, label) => {
    const vals = names.map(k => loops[k][key]).flat().concat(plant, [mark]).filter(Number.isFinite);
    let lo = Math.min(...vals), hi = Math.max(...vals); const pad = (hi - lo) * 0.08 || 1; lo -= pad; hi += pad;
    const Y = y => top + ph - ph * (y - lo) / (hi - lo);
    ctx.font = '11px sans-serif'; ctx.lineWidth = 1; ctx.strokeStyle = '#e3e6ea'; ctx.fillStyle = '#555'; ctx.setLineDash([]);
    const yt = niceTicks(lo, hi, 4);
    gridY(ctx, yt, Y, L, W - R);
    xt.forEach(w => { ctx.beginPath(); ctx.moveTo(X(w), top); ctx.lineTo(X(w), top + ph); ctx.stroke(); });
    ctx.textAlign = 'left'; ctx.fillText(label, L + 4, top - 4);
    ctx.strokeStyle = '#b3261e'; ctx.setLineDash([4, 3]); ctx.beginPath(); ctx.moveTo(L, Y(mark)); ctx.lineTo(W - R, Y(mark)); ctx.stroke();
    if (Number.isFinite(wcTuned)) { ctx.beginPath(); ctx.moveTo(X(wcTuned), top); ctx.lineTo(X(wcTuned), top + ph); ctx.stroke(); }
    ctx.setLineDash([]);
    names.forEach(k => {
      const q = loops[k]; ctx.strokeStyle = LOOP_COLORS[k] || '#333'; ctx.lineWidth = 1.8; ctx.beginPath();
      let pen = false;
      q.w_rad_s.forEach((w, i) => { const y = q[key][i]; if (!Number.isFinite(y)) { pen = false; return; }
        pen ? ctx.lineTo(X(w), Y(y)) : ctx.moveTo(X(w), Y(y)); pen = true; });
      ctx.stroke();
    });
    ctx.fillStyle = '#2ca02c';
    frf.w_rad_s.forEach((w, i) => { if (Number.isFinite(plant[i])) { ctx.beginPath(); ctx.arc(X(w), Y(plant[i]), 3.5, 0, 6.3); ctx.fill(); } });
    return yt;
  };
  const gt = panel(T, 'gain_db', frf.gain_db, 0, 'gain [dB]');
  panel(T + ph + gap, 'phase_deg', frf.phase_deg, -180, 'phase [°]');
  ctx.fillStyle = '#555'; ctx.textAlign = 'center';
  xt.forEach(w => ctx.fillText(String(+w.toPrecision(2)), X(w), H - B + 13));
  ctx.textAlign = 'right'; ctx.fillText('ω [rad/s]', W - R, H - 3); ctx.textAlign = 'left';
  c.dataset.lines = names.length; c.dataset.points = frf.w_rad_s.length; c.dataset.ticks = gt.ticks.join(' ');
  const coh = frf.coherence.map(x => fmt(x, 2)).join(', ');
  $('bode-legend').replaceChildren(...names.map(k => legendItem('—', LOOP_COLORS[k] || '#333', `C·G, ${k}`)),
    legendItem('●', '#2ca02c', `plant G measured (coherence ${coh})`),
    legendItem('┄┄', '#b3261e', '0 dB, −180° and the tuned crossover'));
}

// A friction identification, as the thesis GUI's "estimated parameter results" and "friction torque-speed
// curve" (Fig 3.19), with what the GUI did not say: each parameter's 95 % interval (one running onto a
// bound of Table 3.4/3.6 is not pinned down by these tests), the tests the fit could use, and the
// Coulomb + viscous fit beside the Stribeck one on the same points (SPEC §6: show both)
function frictionKeys(rot) {
  return rot ? [['Ts', 'T_s', 'fs', 'N·m'], ['Tc', 'T_c', 'fc', 'N·m'], ['ws', 'ω_s', 'vs', 'rad/s'], ['B', 'B', 'b', 'N·m·s/rad']]
             : [['Fs', 'F_s', 'fs', 'N'], ['Fc', 'F_c', 'fc', 'N'], ['vs', 'v_s', 'vs', 'm/s'], ['B', 'B', 'b', 'N·s/m']];
}
function showFriction(lr) {
  const r = lr.result, p = r.parameters, fits = r.fits || {};
  const rot = 'ccw' in p;
  const dirs = rot ? [['ccw', 'Pronation (CCW)'], ['cw', 'Supination (CW)']] : [['extension', 'Extension'], ['retraction', 'Retraction']];
  const keys = frictionKeys(rot);
  const fu = rot ? 'N·m' : 'N', vu = rot ? 'rad/s' : 'm/s', bu = rot ? 'N·m·s/rad' : 'N·s/m';
  // an interval's end on a bound such as 1e-6 reads better as a power of ten than as 0.00000100
  const num = (v, n) => (typeof v === 'number' && v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(n - 1) : fmt(v, n);
  let loose = false;
  const cell = (d, [k, sym, ci]) => {
    const f = fits[d] || {}, iv = (f.ci || {})[ci];
    let html = fmt(p[d][k], 4) + (ci === 'fs' && f.fs_sd != null ? ` ± ${fmt(f.fs_sd, 2)} (SD)` : '');
    if ((f.at_bound || []).includes(ci)) html += ' <small class="bad">on its bound</small>';
    if (iv) {
      loose = loose || iv.at_bound;
      html += `<br><small class="${iv.at_bound ? 'bad loose' : 'muted'}" title="95 % interval of ${sym} (${esc(iv.method)})">` +
              `95 %: ${num(iv.lo, 3)} … ${num(iv.hi, 3)}${iv.at_bound ? ' *' : ''}</small>`;
    }
    return `<td data-param="${ci}">${html}</td>`;
  };
  const MODEL = {stribeck: 'Stribeck', coulomb_viscous: 'Coulomb + viscous'};
  const notes = dirs.map(([d, l]) => {
    const f = fits[d];
    if (!f) return '';
    let t = `${l}: ${f.n_static} breakaway and ${f.n_dynamic} moving tests used (speeds ${fmt(f.speed_range[0], 3)}–` +
            `${fmt(f.speed_range[1], 3)} ${vu}), fit RMS ${fmt(f.rmse, 2)} ${fu}.`;
    const c = f.choice;
    if (c) {
      t += c.selected === 'stribeck'
        ? ` Stribeck fits these points better than Coulomb + viscous (AICc ${fmt(c.aicc_stribeck, 3)} against ${fmt(c.aicc_cv, 3)}).`
        : ` Coulomb + viscous is enough here (AICc ${fmt(c.aicc_cv, 3)} against Stribeck's ${fmt(c.aicc_stribeck, 3)}).`;
      t += ` Coulomb + viscous alone: ${rot ? 'T_c' : 'F_c'} ${fmt(c.cv_fc, 4)} ${fu}, B ${fmt(c.cv_b, 4)} ${bu}.` +
           ` The thesis GUI's rule would say: ${MODEL[c.thesis_rule] || esc(c.thesis_rule)}.`;
    }
    return `<li data-dir="${d}">${esc(t)}</li>`;
  }).join('');
  const mass = typeof r.moving_mass_kg === 'number' && r.moving_mass_kg > 0
    ? `<p class="muted">Moving mass fitted for the inertia correction: ${fmt(r.moving_mass_kg, 3)} kg.</p>` : '';
  const rows = dirs.map(([d, l]) => `<tr data-dir="${d}"><td>${l}</td>` + keys.map(k => cell(d, k)).join('') + '</tr>').join('');
  const star = loose ? `<li id="ident-loose">* An interval that runs onto a bound of Table ${rot ? '3.4' : '3.6'}: ` +
    'these tests do not pin that parameter down.</li>' : '';
  $('last').innerHTML = `<p>Identification ${esc(lr.run_id)}: ${esc(lr.status)}` +
    (r.tests ? ` — ${r.tests.static} breakaway and ${r.tests.dynamic} moving tests run` : '') + '</p>' +
    `<div class="wide"><table id="ident-result"><tr><th></th>` +
    keys.map(([, sym, , unit]) => `<th>${sym} [${unit}]</th>`).join('') + `</tr>${rows}</table></div>` +
    `<ul id="ident-notes">${notes}${star}</ul>${mass}`;
  if (r.points) drawFriction(p, r.points, dirs.map(([d]) => d), rot, fits);
}
function drawFriction(p, pts, dirs, rot, fits = {}) {
  const c = $('c-friction'); c.hidden = $('friction-legend').hidden = false;
  $('friction-cv').hidden = !dirs.some(d => (fits[d] || {}).choice);
  const {ctx, W, H} = fitCanvas(c);
  const K = frictionKeys(rot).map(([k]) => k);
  const vmax = Math.max(1e-3, ...pts.dynamic.map(q => Math.abs(q[0]))) * 1.1;
  const stribeck = (d, v) => { const [fs, fc, vs, b] = K.map(k => p[d][k]); return fc + (fs - fc) * Math.exp(-((v / vs) ** 2)) + b * v; };
  const cv = (d, v) => { const m = (fits[d] || {}).choice; return m ? m.cv_fc + m.cv_b * v : null; };
  // each direction's curves on its own side of zero speed, sampled where the chart draws them
  const curves = dirs.map((d, i) => {
    const v = Array.from({length: 100}, (_, k) => (i === 0 ? 1 : -1) * vmax * (k + 1) / 100);
    return {st: v.map(x => [x, stribeck(d, x)]), cv: (fits[d] || {}).choice ? v.map(x => [x, cv(d, x)]) : null};
  });
  const ys = pts.dynamic.map(q => q[1]).concat(pts.static.map(q => q[1]), dirs.map(d => p[d][K[0]]),
    ...curves.map(cu => cu.st.concat(cu.cv || []).map(q => q[1]))).filter(Number.isFinite);
  let lo = Math.min(0, ...ys), hi = Math.max(0, ...ys); const pad = (hi - lo) * 0.06 || 1; lo -= pad; hi += pad;
  const L = 46, R = 10, T = 18, B = 32;
  const X = v => L + (W - L - R) * (v + vmax) / (2 * vmax), Y = y => H - B - (H - B - T) * (y - lo) / (hi - lo);
  ctx.font = '11px sans-serif'; ctx.lineWidth = 1; ctx.strokeStyle = '#e3e6ea'; ctx.fillStyle = '#555';
  const yt = niceTicks(lo, hi, 4), xt = niceTicks(-vmax, vmax, 6);
  gridY(ctx, yt, Y, L, W - R); gridX(ctx, xt, X, T, H - B);
  c.dataset.ticks = yt.ticks.map(y => y.toFixed(yt.digits)).join(' ');
  c.dataset.vticks = xt.ticks.map(v => v.toFixed(xt.digits)).join(' ');
  ctx.strokeStyle = '#aaa';
  [[X(-vmax), Y(0), X(vmax), Y(0)], [X(0), Y(lo), X(0), Y(hi)]].forEach(([a, b, cc, d]) => { ctx.beginPath(); ctx.moveTo(a, b); ctx.lineTo(cc, d); ctx.stroke(); });
  ctx.textAlign = 'left'; ctx.fillText(rot ? 'friction torque [N·m]' : 'friction force [N]', 4, 11);
  ctx.textAlign = 'right'; ctx.fillText(rot ? 'speed [rad/s]' : 'speed [m/s]', W - R, H - 3);
  ctx.textAlign = 'left';
  const line = (q, color, width, dash) => {
    ctx.strokeStyle = color; ctx.lineWidth = width; ctx.setLineDash(dash); ctx.beginPath();
    q.forEach(([v, y], k) => k === 0 ? ctx.moveTo(X(v), Y(y)) : ctx.lineTo(X(v), Y(y))); ctx.stroke(); ctx.setLineDash([]);
  };
  ctx.save(); ctx.beginPath(); ctx.rect(L, T, W - L - R, H - B - T); ctx.clip();
  curves.forEach(cu => { if (cu.cv) line(cu.cv, '#999', 1.4, [6, 4]); line(cu.st, '#333', 1.8, []); });
  ctx.fillStyle = '#1f77b4'; pts.dynamic.forEach(([v, y]) => { ctx.beginPath(); ctx.arc(X(v), Y(y), 2.5, 0, 6.3); ctx.fill(); });
  // diamonds, as the legend shows them (squares had been drawn under a ◆ legend)
  ctx.fillStyle = '#d62728';
  pts.static.forEach(([, y]) => {
    const x0 = X(0), y0 = Y(y);
    ctx.beginPath(); ctx.moveTo(x0, y0 - 4); ctx.lineTo(x0 + 4, y0); ctx.lineTo(x0, y0 + 4); ctx.lineTo(x0 - 4, y0); ctx.closePath(); ctx.fill();
  });
  ctx.restore();
  c.dataset.points = pts.dynamic.length + pts.static.length;
}

// identification, tuning, calibration and parameter sets are an admin's (docs/station.md, "The REST API"):
// a therapist's tab shows them but offers no button that would answer 403
let signedIn = {required: false, role: null};
const isAdmin = () => !signedIn.required || signedIn.role === 'admin';
async function whoami() {
  const a = await api('GET', '/api/auth');
  signedIn = a;
  $('signin').hidden = !a.required || a.role !== null;
  $('who').textContent = a.required ? (a.role ? `signed in: ${a.role}` : 'not signed in') : '';
  return a;
}
$('signin-btn').addEventListener('click', async () => {
  sessionStorage.setItem('cwrr-token', $('token').value.trim());
  $('token').value = '';
  let a;
  try { a = await whoami(); }
  catch (e) { sessionStorage.removeItem('cwrr-token'); $('who').textContent = `not signed in: ${e.message}`; return; }
  if (a.role === null) { sessionStorage.removeItem('cwrr-token'); $('who').textContent = 'token not accepted'; }
  else { poll(); checkForm(); loadRuns(); loadSets(); showViser(); }
});

document.querySelectorAll('.cal').forEach(b => b.addEventListener('click', async () => {
  say('cal-msg', 'Calibrating…', true);
  try {
    const r = await api('POST', '/api/engine/calibrate', {what: b.dataset.cal});
    say('cal-msg', `${r.what}: ${JSON.stringify(r.before)} → ${JSON.stringify(r.after)} (${r.samples} samples)`, true);
  } catch (e) { say('cal-msg', e.message, false); }
}));

$('estop').addEventListener('click', () => pressEstop(render));

async function poll() {
  try { render(await api('GET', '/api/engine')); }
  catch (e) { showNoState(e.status === 401 || e.status === 403 ? 'sign in' : 'server not reachable'); }
}

document.querySelectorAll('[data-action]').forEach(b => b.addEventListener('click', async () => {
  const a = b.dataset.action;
  try {
    if (a === 'start') {
      const body = {scenario: $('scenario').value, controller: $('controller').value,
                    target_nm: parseFloat($('target').value), person: $('person').value.trim(), notes: $('notes').value};
      if ($('session').value) body.session_id = parseInt($('session').value);
      if ($('gains-set').value) body.gains_id = parseInt($('gains-set').value);
      if ($('workout-set').value) body.workout_id = parseInt($('workout-set').value);
      const r = await api('POST', '/api/engine/start', body);
      say('start-msg', `Exercise started (run ${r.run_id}).`, true);
      $('start-msg').dataset.run = r.run_id;  // said again in other words when it ends
      render(r.status);
    } else if (a === 'connect') {
      const [rig, cylinder] = $('rig').value.split(':');
      render(await api('POST', '/api/engine/connect', cylinder ? {rig, cylinder} : {rig}));
    } else if (b.id === 'estimate-dcv') {
      const quick = $('dcv-grid').value === 'quick';
      const body = quick ? {ps_bar: [5], u_fill: [4.6, 4.8, 5.0, 5.2, 5.4], u_exh: [4.8, 5.0, 5.2, 5.4, 5.6]} : {};
      if ($('dcv-validate').checked) body.validation = ['filling', 'exhausting'].flatMap(m => [4.7, 5.0, 5.3].map(u => [m, u, 5]));
      const r = await api('POST', '/api/engine/estimate/dcv', body);
      say('dcv-msg', `Experiments are started (${r.status.progress.total_tests}), please wait to complete!`, true); render(r.status);
    } else if (b.id === 'tune-pid') {
      const body = {side: $('pid-side').value, bandwidth_rad_s: parseFloat($('pid-bw').value),
                    phase_margin_deg: parseFloat($('pid-pm').value), pw_bar: parseFloat($('pid-pw').value)};
      const r = await api('POST', '/api/engine/tune/pid', body);
      say('pid-msg', 'Tuning experiment started, please wait to complete!', true); render(r.status);
    } else if (a === 'estimate') {
      const r = await api('POST', `/api/engine/estimate/${identRig}`, identValues());
      say('ident-msg', 'Experiments are started, please wait to complete!', true); render(r.status);
    } else {
      render(await api('POST', `/api/engine/${a}`));
    }
  } catch (e) {
    const box = {'estimate-dcv': 'dcv-msg', 'tune-pid': 'pid-msg', estimate: 'ident-msg'}[b.id] || 'start-msg';
    say(box, e.message, false);
  }
}));

// ------------------------------------------------------- guided forms (thesis Appendices 1 and 2)
function identValues() {
  const v = {};
  document.querySelectorAll('#ident-fields input').forEach(i => { if (i.value !== '') v[i.name] = parseFloat(i.value); });
  return v;
}
async function checkForm() {
  const v = identValues();
  const rig = identRig, cylinder = identCyl;
  let st;
  try { st = await api('POST', `/api/forms/${rig}`, {values: v, cylinder}); }
  catch (e) {
    // unchecked, the form is not ready: Run identification stays off until the station answers
    if (rig === identRig) { say('ident-msg', `The form could not be checked: ${e.message}`, false); identReady = false; render(status); }
    return;
  }
  const box = $('ident-fields');
  if (rig !== identRig || cylinder !== identCyl) return;  // the rig changed while the form was being checked
  $('ident-title').textContent = `Friction identification (${rig === 'rotary' ? 'rotary, forearm robot' : `linear test cylinder ${cylinder}`})`;
  if (!box.children.length) {
    box.innerHTML = st.fields.map(f =>
      `<label for="f-${f.name}">${esc(f.label)}</label><input id="f-${f.name}" name="${f.name}" type="number" step="any">`
    ).join('');
    box.querySelectorAll('input').forEach(i => i.addEventListener('change', checkForm));
    return checkForm();
  }
  st.fields.forEach(f => {
    const i = $('f-' + f.name);
    i.classList.toggle('valid', f.valid);
    i.disabled = !f.editable;  // thesis GUI: a valid field turns green and locks; Clear starts over
    // the station's suggestion: on the linear rig, the chosen cylinder's catalogue geometry
    i.placeholder = f.editable && i.value === '' ? `suggested: ${f.suggested}` : '';
  });
  say('ident-msg', st.message, !st.refused);
  identReady = st.ready;
  if (st.ready) { $('ident-msg').dataset.ready = st.message; }
  render(status);
}

// ------------------------------------------------------------------------- live charts
let live = [];
let since = -1;
// Gridlines at round values (1, 2, 2.5 or 5 × 10^k apart, about n of them), so that an axis reads
// 0, 0.5, 1.0, 1.5 and not 0.11, 0.54, 0.97 (the span cut in four). Returns the values and the
// decimals their labels need.
// a chart is drawn at the size it is shown: a 900-px drawing squeezed into a phone's 350 px squeezes its
// labels too. The canvas's pixels are set to its shown size, and it comes back cleared
function fitCanvas(canvas) {
  const cw = Math.round(canvas.clientWidth), ch = Math.round(canvas.clientHeight);
  if (cw > 0 && ch > 0 && (canvas.width !== cw || canvas.height !== ch)) { canvas.width = cw; canvas.height = ch; }
  const ctx = canvas.getContext('2d'); const W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  return {ctx, W, H};
}
// a result chart's gridlines at niceTicks' values, in the colours the caller set: horizontal ones from x0
// to x1 labelled left of x0, vertical ones from y0 to y1 labelled under y1 (a −0 reads 0)
function gridY(ctx, yt, Y, x0, x1) {
  ctx.textAlign = 'right';
  yt.ticks.forEach(y => { ctx.beginPath(); ctx.moveTo(x0, Y(y)); ctx.lineTo(x1, Y(y)); ctx.stroke();
                         ctx.fillText(tickLabel(y, yt.digits), x0 - 4, Y(y) + 4); });
  ctx.textAlign = 'left';
}
function gridX(ctx, xt, X, y0, y1) {
  ctx.textAlign = 'center';
  xt.ticks.forEach(x => { ctx.beginPath(); ctx.moveTo(X(x), y0); ctx.lineTo(X(x), y1); ctx.stroke();
                         ctx.fillText(tickLabel(x, xt.digits), X(x), y1 + 13); });
  ctx.textAlign = 'left';
}
// rows: [t, column 1, column 2, ...]; shade: a time span [s] to tint (a run's scored window)
function draw(canvas, series, lo, hi, rows = live, shade = null) {
  const {ctx, W, H} = fitCanvas(canvas);
  if (rows.length < 2) return;
  const t0 = rows[0][0], t1 = rows[rows.length - 1][0];
  let ymin = lo, ymax = hi;
  series.forEach(([c]) => rows.forEach(r => { if (r[c] !== null) { ymin = Math.min(ymin, r[c]); ymax = Math.max(ymax, r[c]); } }));
  const pad = (ymax - ymin) * 0.08 || 1; ymin -= pad; ymax += pad;
  const X = t => 40 + (W - 50) * (t - t0) / Math.max(t1 - t0, 1e-6), Y = y => H - 20 - (H - 30) * (y - ymin) / (ymax - ymin);
  if (shade) {
    const a = X(Math.max(shade[0], t0)), b = X(Math.min(shade[1], t1));
    ctx.fillStyle = 'rgba(90,127,168,0.14)'; ctx.fillRect(a, 10, Math.max(b - a, 0), H - 30);
  }
  ctx.strokeStyle = '#ccc'; ctx.fillStyle = '#555'; ctx.font = '11px sans-serif'; ctx.lineWidth = 1;
  const {ticks, digits} = niceTicks(ymin, ymax);
  ticks.forEach(y => {
    ctx.beginPath(); ctx.moveTo(40, Y(y)); ctx.lineTo(W - 10, Y(y)); ctx.stroke();
    ctx.fillText((Math.abs(y) < 1e-12 ? 0 : y).toFixed(digits), 2, Y(y) + 4);
  });
  canvas.dataset.ticks = ticks.map(y => y.toFixed(digits)).join(' ');
  ctx.fillText(`${(t1 - t0).toFixed(1)} s`, W - 50, H - 4);
  series.forEach(([c, color, dash]) => {
    ctx.strokeStyle = color; ctx.lineWidth = 1.6; ctx.setLineDash(dash ? [6, 4] : []); ctx.beginPath();
    let pen = false;
    rows.forEach(r => { if (r[c] === null) { pen = false; return; } const x = X(r[0]), y = Y(r[c]); pen ? ctx.lineTo(x, y) : ctx.moveTo(x, y); pen = true; });
    ctx.stroke();
  });
  ctx.setLineDash([]);
}
// the handle's angle on a bar spanning the range of motion, end stops at its ends and the no-action zone
// inside each drawn as the station's safety applies them; on the linear set-ups the piston's travel along
// the cylinder's stroke (retracted at the left). Built when the limits or the rig change, moved per poll
let gaugeKey = null, gaugeHalf = 0, gaugeStroke = null;
function setGauge(lim, rig) {
  const stroke = rig && rig.kind !== 'rotary' && typeof rig.stroke_mm === 'number' ? rig.stroke_mm : null;
  const rom = stroke === null && lim && typeof lim.rom_deg === 'number' ? lim.rom_deg : null;
  const key = stroke !== null ? `stroke/${stroke}` : rom === null ? null : `${rom}/${lim.soft_margin_deg}`;
  if (key === gaugeKey) return;
  gaugeKey = key; gaugeStroke = stroke; $('handle-gauge').hidden = key === null;
  if (key === null) return;
  gaugeHalf = rom === null ? 0 : rom / 2;
  const soft = rom === null ? 0 : 100 * lim.soft_margin_deg / rom;
  $('handle-svg').setAttribute('aria-label', stroke === null ? "The handle's angle between the end stops"
    : "The piston's travel along the cylinder's stroke");
  $('gauge-caption').textContent = stroke === null
    ? 'left: supination · right: pronation · orange: no-action zone before each end stop'
    : `left: retracted · right: extended (${stroke} mm, the ${rig.cylinder} stroke)`;
  $('handle-svg').innerHTML =
    `<rect x="0" y="9" width="100%" height="8" fill="#e6ebf1"/>` +
    (soft > 0 ? `<rect x="0" y="9" width="${soft}%" height="8" fill="#f0a040"/><rect x="${100 - soft}%" y="9" width="${soft}%" height="8" fill="#f0a040"/>` : '') +
    `<rect x="0" y="3" width="3" height="20" fill="#d62728"/><rect x="100%" y="3" width="3" height="20" fill="#d62728" transform="translate(-3,0)"/>` +
    (stroke === null ? `<rect x="50%" y="6" width="1" height="14" fill="#888"/>` : '') +
    `<rect id="handle-mark" x="${stroke === null ? 50 : 0}%" y="1" width="6" height="24" rx="2" fill="#1f77b4" transform="translate(-3,0)" visibility="hidden"/>`;
  $('handle-angle').textContent = '';
}
// pos: the measured angle [rad] on the forearm robot, the piston's travel [m] on the linear set-ups
function moveGauge(pos) {
  if (gaugeKey === null || !Number.isFinite(pos)) return;
  const m = $('handle-mark');
  let pct;
  if (gaugeStroke !== null) {
    const mm = pos * 1000;
    pct = Math.min(100, Math.max(0, 100 * mm / gaugeStroke));
    m.dataset.mm = mm.toFixed(1); delete m.dataset.deg;
    $('handle-angle').textContent = `Piston: ${Math.round(mm)} of ${gaugeStroke} mm extended`;
  } else {
    const deg = pos * 180 / Math.PI;
    pct = Math.min(100, Math.max(0, 50 + 50 * deg / gaugeHalf));
    m.dataset.deg = deg.toFixed(2); delete m.dataset.mm;
    $('handle-angle').textContent = `Handle: ${angleWords(deg)}`;
  }
  m.setAttribute('x', `${pct.toFixed(2)}%`); m.setAttribute('visibility', 'visible');
}
async function pollLive() {
  try {
    const d = await api('GET', `/api/live?since=${since}&max_rows=3000`);
    if (d.rows.length) {
      const last = live.length ? live[live.length - 1][0] : -Infinity;
      live = live.concat(d.rows.filter(r => r[0] > last)); since = d.t_last;
      const cut = since - 10; live = live.filter(r => r[0] >= cut);
      draw($('c-torque'), [[1, '#1f77b4'], [2, '#d62728', true]], -0.2, 0.2);
      draw($('c-press'), [[3, '#2ca02c'], [5, '#2ca02c', true], [4, '#9467bd'], [6, '#9467bd', true]], 1, 1.2);
      $('c-torque').dataset.samples = live.length;
      const ith = d.columns.indexOf('theta');
      if (ith >= 0) moveGauge(d.rows[d.rows.length - 1][ith]);
    } else if (d.t_last < since) { since = -1; live = []; }  // a new connection restarts the time axis
  } catch (e) { /* the state poll reports an unreachable server */ }
}

// ------------------------------------------------------------------------------- history
// a page of 50, newest first; a person's id narrows it (the same characters a run's person may have)
const PAGE = 50;
let histOffset = 0, shownRun = null;  // shownRun: the history's run whose result "Last result" shows
async function loadRuns() {
  const who = $('hist-person').value.trim();
  if (!/^[A-Za-z0-9_.-]*$/.test(who)) {
    $('hist-msg').className = 'msg bad'; $('hist-msg').textContent = 'A person id has letters, digits, "-", "_" and "." only.';
    return;
  }
  const q = new URLSearchParams({limit: PAGE + 1, offset: histOffset, with_result: false});  // a click fetches one
  if (who) q.set('person', who);
  let page;
  try { page = await api('GET', `/api/runs?${q}`); }
  catch (e) { $('hist-msg').className = 'msg bad'; $('hist-msg').textContent = `The run history could not be loaded: ${e.message}`; return; }
  const runs = page.slice(0, PAGE);
  $('hist-older').disabled = page.length <= PAGE; $('hist-newer').disabled = histOffset === 0;
  $('hist-msg').className = 'msg';
  $('hist-msg').textContent = runs.length ? `runs ${histOffset + 1}–${histOffset + runs.length}${who ? ` of ${who}` : ''}`
                                          : (who ? `no runs of ${who}` : 'no runs yet');
  drawProgress(who).catch(() => { $('progress-chart').hidden = true; });
  $('runs').querySelector('tbody').innerHTML = runs.map(r => {
    const KINDS = {rotary_friction: 'Friction identification (rotary)', linear_friction: 'Friction identification (linear)',
                   dcv_flow: 'Valve map and flow model', pid_tuning: `Pressure-loop tuning, PRV-${r.spec.side}`,
                   diagnosis: 'Gap diagnosis', imported: `Imported log ${r.spec.name}`,
                   diagnosis_protocol: 'Diagnosis protocol on the rig', protocol: `Protocol log ${r.spec.log}`};
    const what = r.kind === 'workout' ? exerciseWhat(r.spec) : (KINDS[r.kind] || r.kind);
    // only workouts carry the six metrics; a diagnosis's metrics are other numbers
    const mae = r.metrics && typeof r.metrics.mae === 'number' ? r.metrics.mae.toPrecision(3) : '';
    const exp = r.has_series ? ['csv', 'parquet', 'mat'].map(f => `<a href="/api/runs/${r.id}/export?fmt=${f}" download>${f === 'mat' ? 'MATLAB' : f.toUpperCase()}</a>`).join(' · ') : '';
    // plain words for the therapist; the API's code (what /api/runs?kind= takes) stays in the tooltip
    const group = KIND_GROUPS[r.kind] || r.kind;
    return `<tr data-run="${r.id}"${r.id === shownRun ? ' class="shown"' : ''}><td><a href="#" data-open-run aria-label="run ${r.id}: show its result">${r.id}</a></td><td title="kind=${esc(r.kind)}">${esc(group)}</td><td>${esc(what)}</td><td>${esc(r.person)}</td><td>${esc(r.status)}</td><td>${mae}</td><td>${exp}</td></tr>`;
  }).join('');
}

const KIND_GROUPS = {workout: 'Exercise', rotary_friction: 'Identification', linear_friction: 'Identification',
                     dcv_flow: 'Identification', pid_tuning: 'Tuning', diagnosis: 'Diagnosis',
                     diagnosis_protocol: 'Diagnosis', protocol: 'Diagnosis', imported: 'Imported log'};

$('hist-person').addEventListener('change', () => { histOffset = 0; loadRuns(); });

// one person's progress: the MAE of each exercise that ran to its end, oldest first, a colour per
// scenario (a stopped run is scored over what it reached, so it is left out)
async function drawProgress(who) {
  const box = $('progress-chart');
  // with their results (an exercise's is a few hundred bytes): the range of motion each reached
  const all = who ? await api('GET', `/api/runs?kind=workout&limit=200&with_result=true&person=${encodeURIComponent(who)}`) : [];
  const runs = all.filter(r => r.status === 'complete' && r.metrics && typeof r.metrics.mae === 'number').reverse();
  box.hidden = !runs.length;
  if (!runs.length) { box.innerHTML = ''; return; }
  const vmax = Math.max(...runs.map(r => r.metrics.mae)), W = box.clientWidth || 600, H = 160, pad = 36, top = vmax * 1.15;
  const COL = {'SC-1': '#1f77b4', 'SC-2': '#2ca02c', 'SC-3': '#ff7f0e', 'SC-4': '#9467bd'};
  const x = i => pad + (runs.length === 1 ? (W - 2 * pad) / 2 : i * (W - 2 * pad) / (runs.length - 1));
  const y = v => H - pad + 10 - (H - pad) * v / top;
  let svg = `<line x1="${pad}" x2="${W - pad}" y1="${y(0)}" y2="${y(0)}" stroke="#d5dbe3"/>` +
    `<text x="4" y="${y(vmax) + 4}" font-size="11">${vmax.toPrecision(2)}</text>` +
    `<text x="4" y="${y(0) + 4}" font-size="11">0</text>`;
  runs.forEach((r, i) => {
    const when = new Date(r.started * 1000).toLocaleString();
    svg += `<circle cx="${x(i)}" cy="${y(r.metrics.mae)}" r="4" fill="${COL[r.spec.scenario] || '#333'}"><title>run ${r.id}, ${esc(when)}: ` +
      `${esc(exerciseWhat(r.spec))} — MAE ${r.metrics.mae.toPrecision(3)} N·m</title></circle>`;
  });
  const seen = [...new Set(runs.map(r => r.spec.scenario))];
  svg += seen.map((sc, k) => `<rect x="${pad + k * 70}" y="2" width="10" height="10" fill="${COL[sc] || '#333'}"/>` +
    `<text x="${pad + 14 + k * 70}" y="11" font-size="11">${esc(sc)}</text>`).join('');
  const span = all.length === 200 ? ' among their latest 200' : '';
  box.innerHTML = `<div style="font-size:.85rem;color:var(--muted)">Progress of ${esc(who)}: MAE [N·m] of each complete exercise${span}, oldest first</div>` +
    `<svg width="${W}" height="${H}" role="img" aria-label="progress">${svg}</svg>` + rangeProgress(runs, x, W, pad, COL) +
    `<p class="msg"><a id="progress-csv" href="/api/exercises?person=${encodeURIComponent(who)}" download>` +
    `All of ${esc(who)}'s exercises as a table (CSV: date, exercise, how it ended, metrics, range of motion, notes)</a></p>`;
}
// under the MAE, at the same places: the range of motion each of those exercises reached, a bar from its
// lowest to its highest angle (runs stored before the station recorded it have none)
function rangeProgress(runs, x, W, pad, COL) {
  const has = runs.map(r => r.result && Array.isArray(r.result.angle_range_deg) ? r.result.angle_range_deg : null);
  const got = has.filter(Boolean);
  if (!got.length) return '';
  const H = 140, lo = Math.min(0, ...got.map(a => a[0])), hi = Math.max(0, ...got.map(a => a[1]));
  const top = hi + 0.1 * (hi - lo || 1), bottom = lo - 0.1 * (hi - lo || 1);
  const y = v => 8 + (H - 24) * (top - v) / (top - bottom);
  let svg = `<line x1="${pad}" x2="${W - pad}" y1="${y(0)}" y2="${y(0)}" stroke="#d5dbe3"/>` +
    `<text x="4" y="${y(0) + 4}" font-size="11">0°</text>` +
    (hi > 0 ? `<text x="4" y="${y(hi) + 4}" font-size="11">${Math.round(hi)}°</text>` : '') +
    (lo < 0 ? `<text x="4" y="${y(lo) + 4}" font-size="11">${Math.round(lo)}°</text>` : '');
  runs.forEach((r, i) => {
    const a = has[i];
    if (!a) return;
    svg += `<rect x="${x(i) - 3}" y="${y(a[1])}" width="6" height="${Math.max(1, y(a[0]) - y(a[1]))}" fill="${COL[r.spec.scenario] || '#333'}">` +
      `<title>run ${r.id}: ${esc(rangeWords(a))}</title></rect>`;
  });
  return `<div style="font-size:.85rem;color:var(--muted)">Range of motion reached [°] by the same exercises (positive: pronation)</div>` +
    `<svg width="${W}" height="${H}" role="img" aria-label="range of motion">${svg}</svg>`;
}

// ------------------------------------------------------------------------------- therapy sessions
// the person's sessions, newest first; a run started with one is stored under it (and must be theirs)
let sessionNotes = {}, notesTyped = false;  // session id → its stored notes; unsaved typing in the field
$('session-notes').addEventListener('input', () => { notesTyped = true; });
async function loadSessions(select) {
  const who = $('person').value.trim(), sel = $('session'), before = sel.value;
  sel.querySelectorAll('option[value]:not([value=""])').forEach(o => o.remove());
  sessionNotes = {};
  if (!who || !/^[A-Za-z0-9_.-]+$/.test(who)) { sel.value = ''; showSessionNotes(); return; }
  const list = await api('GET', `/api/sessions?person=${encodeURIComponent(who)}`).catch(() => []);
  list.forEach(x => {
    const o = document.createElement('option'); o.value = x.id;
    // the count before the notes, and the time to the minute: the picker is a column wide, and the
    // end of a long label ("… (2 runs)") was cut off
    const when = new Date(x.created * 1000).toLocaleString([], {dateStyle: 'medium', timeStyle: 'short'});
    o.textContent = `#${x.id} · ${when} · ${x.runs.length} run${x.runs.length === 1 ? '' : 's'}` +
      (x.notes ? ` · ${x.notes.slice(0, 40)}` : '');
    sessionNotes[x.id] = x.notes;
    sel.appendChild(o);
  });
  sel.value = select !== undefined ? String(select) : '';
  // a refresh (a run's end recounts the runs) keeps what is being typed about the same session
  showSessionNotes(notesTyped && sel.value === before);
}
// with a session chosen the field holds its notes, to be completed after the exercises and saved;
// with none it holds the notes a new session opens with
function showSessionNotes(keepTyped = false) {
  const id = $('session').value, f = $('session-notes');
  $('save-session-notes').hidden = !id;
  if (!keepTyped) { f.value = id ? (sessionNotes[id] || '') : ''; notesTyped = false; }
  f.placeholder = id ? 'notes of this session (saved with "Save notes")' : 'notes for a new session, e.g. left arm';
}
$('session').addEventListener('change', () => { $('session-msg').textContent = ''; showSessionNotes(); });
$('save-session-notes').addEventListener('click', async () => {
  const id = $('session').value;
  try {
    const x = await api('PATCH', `/api/sessions/${id}`, {notes: $('session-notes').value});
    notesTyped = false;
    await loadSessions(x.id);
    say('session-msg', `Notes of session ${x.id} saved.`, true);
  } catch (e) { say('session-msg', e.message, false); }
});
$('person').addEventListener('change', () => { $('session-msg').textContent = ''; loadSessions(); });
$('new-session').addEventListener('click', async () => {
  try {
    const x = await api('POST', '/api/sessions', {person: $('person').value.trim(), notes: $('session-notes').value});
    notesTyped = false;
    await loadSessions(x.id);
    say('session-msg', `Session ${x.id} opened for ${x.person}.`, true);
  } catch (e) {
    say('session-msg', $('person').value.trim() ? e.message : 'Enter the person id first (letters, digits, "-", "_", ".").', false);
  }
});
$('hist-older').addEventListener('click', () => { histOffset += PAGE; loadRuns(); });
$('hist-newer').addEventListener('click', () => { histOffset = Math.max(0, histOffset - PAGE); loadRuns(); });

// stored parameter sets the exercise can use
async function loadSets() {
  for (const [kind, id] of [['gains', 'gains-set'], ['workout', 'workout-set']]) {
    const sel = $(id), keep = sel.value;
    const sets = await api('GET', `/api/params?kind=${kind}`).catch(() => []);
    sel.querySelectorAll('option[value]:not([value=""])').forEach(o => o.remove());
    sets.forEach(p => { const o = document.createElement('option'); o.value = p.id; o.textContent = `#${p.id} ${p.name}`; sel.appendChild(o); });
    sel.value = keep;
  }
}

// the shown run's notes, to be completed after it (what the person said, how it went); stored with
// when they were changed, beside the notes it started with (kept in its spec)
async function showRunNotes(id, run) {
  const box = $('run-notes-box');
  if (id === undefined || id === null) { box.hidden = true; return; }
  const r = run || await api('GET', `/api/runs/${id}`).catch(() => null);
  if (!r) { box.hidden = true; return; }
  box.dataset.run = r.id; $('run-notes').value = r.notes || ''; $('run-notes-msg').textContent = '';
  $('save-run-notes').textContent = `Save notes on run ${r.id}`;
  box.hidden = false;
}
$('save-run-notes').addEventListener('click', async () => {
  const id = $('run-notes-box').dataset.run;
  try {
    await api('PATCH', `/api/runs/${id}`, {notes: $('run-notes').value});
    say('run-notes-msg', `Notes on run ${id} saved.`, true);
    loadRuns();
  } catch (e) { say('run-notes-msg', e.message, false); }
});
// a click on a run (not on its export links) shows its result where the last one shows; the run's number
// is a link, so that a keyboard reaches it too (Tab, then Enter: a row takes no focus)
$('runs').addEventListener('click', async ev => {
  const tr = ev.target.closest('tr[data-run]');
  const link = ev.target.closest('a');
  if (!tr || (link && !link.hasAttribute('data-open-run'))) return;
  ev.preventDefault();
  try { await showRun(tr.dataset.run); }
  catch (e) { $('hist-msg').className = 'msg bad'; $('hist-msg').textContent = `run ${tr.dataset.run}: ${e.message}`; }
});
// a stored run's result where the last one shows, and its row marked in the history
async function showRun(id) {
  const r = await api('GET', `/api/runs/${id}`);
  if (r.kind === 'diagnosis') {
    hideResultCharts();
    drawTrace(null);
    $('last').innerHTML = esc(`Gap diagnosis ${r.id}: ${r.status}` + (r.result && r.result.verdict ? ` — ${r.result.verdict.summary}` : '')) +
      (r.status === 'complete' ? ` — <a id="open-report" href="/static/diagnosis.html?report=${r.id}">the full report</a>` : '');
  } else showLast({run_id: r.id, status: r.status, metrics: r.metrics, result: r.result, run: r});
  showRunNotes(r.id, r);
  // the rows may have been drawn afresh while the run was fetched (a filter's change on blur): mark by id
  shownRun = r.id;
  $('runs').querySelectorAll('tr[data-run]').forEach(x => x.classList.toggle('shown', x.dataset.run === String(r.id)));
}
// a plain link cannot carry the token: with one, exports are fetched and handed to the browser as a file
async function downloadWithToken(ev) {
  const a = ev.target.closest('a[download]');
  if (!a || !sessionStorage.getItem('cwrr-token')) return;
  ev.preventDefault();
  const r = await fetch(a.href, {headers: authHeaders()}).catch(() => null);
  if (!r) { $('who').textContent = 'export failed: the station did not answer'; return; }
  if (!r.ok) { $('who').textContent = `export refused (${r.status})`; return; }
  const name = (r.headers.get('content-disposition') || '').match(/filename="?([^";]+)/);
  const url = URL.createObjectURL(await r.blob());
  const tmp = document.createElement('a'); tmp.href = url; tmp.download = name ? name[1] : 'run';
  tmp.click(); setTimeout(() => URL.revokeObjectURL(url), 1000);
}
$('runs').addEventListener('click', downloadWithToken);
$('progress-chart').addEventListener('click', downloadWithToken);
// each poll waits for its previous answer: with setInterval, answers taking 350 ms had four
// live requests in flight (tests/test_browser.py); they came back out of order, appended
// samples twice, and a late empty one (t_last < since) looked like a new connection
function every(ms, fn) {
  const tick = async () => {
    const t = performance.now();
    try { await fn(); } finally { setTimeout(tick, Math.max(0, ms - (performance.now() - t))); }
  };
  tick();
}
every(500, poll);
every(100, pollLive);
$('rig').addEventListener('change', () => render(status));
$('ident-clear').addEventListener('click', () => { $('ident-fields').innerHTML = ''; checkForm(); });
// what needs a token waits until the station says the tab may have it
let viserTicketed = false;
function showViser() {
  api('GET', '/api/viser').then(v => {
    if (v.url) { const a = $('viser-link'); a.href = v.url; a.hidden = false; viserTicketed = v.expires_s !== null; }
  }).catch(() => {});
}
// on a station with tokens a link signs a browser in once and only for a minute: each click asks
// for a fresh one (the window opens first, while the click still allows a new window)
$('viser-link').addEventListener('click', async ev => {
  if (!viserTicketed) return;
  ev.preventDefault();
  const w = window.open('', '_blank');
  try { const v = await api('GET', '/api/viser'); if (w) w.location.href = v.url; }
  catch (e) { if (w) w.close(); $('who').textContent = `live plots refused: ${e.message}`; }
});
whoami().then(a => { if (!a.required || a.role) { checkForm(); loadRuns(); loadSets(); showViser(); } }).catch(() => {});
