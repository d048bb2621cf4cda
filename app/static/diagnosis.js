// The gap-diagnosis page (diagnosis.html): its source form, the protocol on the connected rig, log
// uploads, and the report (verdict, how far, which, where, recalibration). What every page shares (the
// header's E-STOP, the token, $ and esc) is in station.js, loaded first.
// the dashboard's sign-in (same tab) holds the token (authHeaders); a station without tokens needs none
watchEngine();
const fmt = v => v === null || v === undefined ? '—' : (Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-3 && v !== 0) ? v.toExponential(2) : (+v).toPrecision(3));
// the protocol table and the effect names are the engine's own (GET /api/diagnoses/protocol), not copies
let meaning = {};  // each candidate effect in plain words, from the engine
// a report shown before this table arrives would lack the effects' plain words: poll() waits for it
const protocolTable = fetch('/api/diagnoses/protocol', {headers: authHeaders()}).then(r => r.ok ? r.json() : Promise.reject(r.status)).then(t => {
  meaning = t.candidate_meaning || {};
  $('effects').innerHTML = t.candidates.map(e =>
    `<label class="cb" title="${esc(meaning[e] || '')}"><input type="checkbox" value="${esc(e)}"> ${esc(e)}</label>`).join('');
  $('tried-effects').innerHTML = t.candidates.map(e =>
    `<label class="cb" title="${esc(meaning[e] || '')}"><input type="checkbox" value="${esc(e)}" checked> ${esc(e)}</label>`).join('');
  $('rkinds').innerHTML = t.experiments.map(e =>
    `<label class="cb"><input type="checkbox" value="${esc(e.name)}" checked> ${esc(e.name)}</label>`).join('');
  $('range-rows').innerHTML = '<tr><th>Parameter</th><th>from</th><th>to</th></tr>' + t.baseline.map(b =>
    `<tr><td title="${esc(b.name)}">${esc(b.meaning)} <small>(default ${fmt(b.low)} … ${fmt(b.high)}, nominal ${fmt(b.nominal)})</small></td>` +
    `<td><input type="number" step="any" data-bound="${esc(b.name)}" data-end="0" data-default="${b.low}" aria-label="${esc(b.name)} from"></td>` +
    `<td><input type="number" step="any" data-bound="${esc(b.name)}" data-end="1" data-default="${b.high}" aria-label="${esc(b.name)} to"></td></tr>`).join('');
  $('protocol').innerHTML += t.experiments.map(e =>
    `<tr><td title="${esc(e.description)}">${esc(e.name)}</td><td>${esc(e.makes_visible.join(', ').replaceAll('_', ' '))}</td></tr>`).join('');
}).catch(s => { $('protocol').innerHTML += `<tr><td colspan="2">the protocol table could not be read (${esc(s)})</td></tr>`; });
$('src').onchange = () => { for (const k of ['protocol', 'runs', 'files', 'rig']) $(k === 'protocol' ? 'proto' : k).hidden = $('src').value !== k; };
// ?runs=12,13,14 (the station's link under a finished protocol): those stored runs, ready to diagnose
{
  const ids = (new URLSearchParams(location.search).get('runs') || '').split(',').map(s => s.trim())
    .filter(s => /^[0-9]+$/.test(s));
  if (ids.length) { $('src').value = 'runs'; $('src').onchange(); $('runids').value = ids.join(', '); }
  // ?report=ID (the station's history): a stored diagnosis, shown as when it completed
  const rid = new URLSearchParams(location.search).get('report') || '';
  if (/^[0-9]+$/.test(rid)) poll(+rid);
}
// a shorter protocol pins the baseline down less: on a 0.3 × run with a vane leak the recalibration
// took the dead volumes to 4.99 × nominal (the leak was still named); said where the length is chosen
for (const id of ['scale', 'rscale']) {
  const note = () => {
    const v = +$(id).value;
    $(id + '-note').hidden = !(v > 0 && v < 1);
    $(id + '-note').textContent = `A protocol ${v} × as long pins the model's nominal values down less: the recalibration ` +
      'may take values far from nominal (the report flags them). 1 or more for a diagnosis to act on.';
  };
  $(id).addEventListener('input', note);
  note();
}
function say(text, cls) { $('msg').textContent = text; $('msg').className = 'msg ' + (cls || ''); }
// a diagnosis is an admin's work: say so at once, not as a 403 after the form is filled in
fetch('/api/auth', {headers: authHeaders()}).then(r => r.json()).then(a => {
  if (!a.required || a.role === 'admin') return;
  $('go').disabled = true;
  $('go').title = 'A gap diagnosis needs the admin role';
  if (new URLSearchParams(location.search).get('report')) return;  // reading a stored report: its own message stays
  say(a.role === 'therapist'
    ? 'A gap diagnosis needs the admin role; this tab is signed in with a therapist token. Sign in with an ' +
      'admin token on the Station page to run one; stored reports open as before.'
    : 'This station needs a token: sign in with an admin token on the Station page to run a gap diagnosis.',
    'bad');
}).catch(() => {});
// a request the station never answered, said as such (the browser's own words are "Failed to fetch")
class NoAnswer extends Error {}
const send = (url, init = {}) => fetch(url, {...init, headers: {...(init.headers || {}), ...authHeaders()}})
  .catch(() => { throw new NoAnswer(`the station did not answer ${init.method || 'GET'} ${url} (is it running?)`); });
$('go').onclick = () => go().catch(e => { if (e instanceof NoAnswer) say(e.message, 'bad'); else throw e; });
async function go() {
  // the candidates to try: all (none sent) unless some were left out
  const boxes = [...document.querySelectorAll('#tried-effects input')];
  const tried = boxes.filter(c => c.checked).map(c => c.value);
  if (!tried.length) { say('tick at least one candidate effect to try', 'bad'); return; }
  // the server checks the ranges before anything runs: one refused only when the diagnosis is posted
  // would come after the rig's protocol
  const bounds = ranges();
  if (bounds) {
    const r = await send('/api/diagnoses/bounds', {method: 'POST',
      headers: {'content-type': 'application/json'}, body: JSON.stringify({bounds})});
    if (!r.ok) { say(await refusal(r), 'bad'); return; }
  }
  let body;
  if ($('src').value === 'protocol') {
    body = {protocol: {effects: [...document.querySelectorAll('#effects input:checked')].map(c => c.value),
      magnitude: +$('mag').value, param_error: +$('perr').value, errors: $('errs').value, seed: +$('seed').value, scale: +$('scale').value}};
  } else if ($('src').value === 'rig') {
    const ids = await onRig();
    if (!ids) return;
    body = {run_ids: ids};
  } else if ($('src').value === 'files') {
    const ids = await upload([...$('logfiles').files]);
    if (!ids) return;
    body = {run_ids: ids};
  } else {
    body = {run_ids: $('runids').value.split(',').map(s => s.trim()).filter(Boolean).map(Number)};
  }
  if (bounds) body.bounds = bounds;
  if (tried.length < boxes.length) body.effects = tried;
  const r = await send('/api/diagnoses', {method: 'POST', headers: {'content-type': 'application/json'}, body: JSON.stringify(body)});
  if (!r.ok) { say(await refusal(r), 'bad'); return; }
  const j = await r.json();
  say(`diagnosis ${j.run_id} running (roughly 15–30 s per 83 s of logs on a 2-core station)…`);
  poll(j.run_id);
}
// what a refused request says (FastAPI's list of field errors, or one message)
async function refusal(r) {
  const j = await r.json().catch(() => ({}));
  return (j.detail && j.detail.map ? j.detail.map(d => d.msg).join('; ') : j.detail) || r.statusText;
}
// a parameter's two range inputs, lower end first
function rangeInputs(name) {
  return ['0', '1'].map(end => document.querySelector(`#range-rows input[data-bound="${name}"][data-end="${end}"]`));
}
// the ranges typed in (an end left empty keeps the default's), or null when none was; the server checks them
function ranges() {
  const out = {};
  document.querySelectorAll('#range-rows input[data-end="0"]').forEach(i => {
    const ends = rangeInputs(i.dataset.bound);
    if (ends.every(e => e.value.trim() === '')) return;
    out[i.dataset.bound] = ends.map(e => e.value.trim() === '' ? +e.dataset.default : +e.value);
  });
  return Object.keys(out).length ? out : null;
}
// the protocol on the connected rig through the engine; the stored experiments' run ids, or null and why
async function onRig() {
  const post = (url, body) => send(url, {method: 'POST', headers: {'content-type': 'application/json'},
    body: JSON.stringify(body)});
  const kinds = [...document.querySelectorAll('#rkinds input:checked')].map(c => c.value);
  if (!kinds.length) { say('pick at least one experiment', 'bad'); return null; }
  const r = await post('/api/engine/protocol', {repetitions: +$('rreps').value, scale: +$('rscale').value, kinds,
                                                person: $('rperson').value.trim()});
  if (!r.ok) { say(await refusal(r), 'bad'); return null; }
  const j = await r.json();
  $('rstop').hidden = false;
  $('rstop').onclick = () => post('/api/engine/stop', {}).catch(e => say(e.message, 'bad'));  // the header's STOP too
  // the header's poll follows the engine (engineSeen): only a state asked for after the protocol started counts
  let st = j.status, since = performance.now();
  while (st.state === 'identifying' || st.state === 'stopping') {
    say(`protocol run ${j.run_id}: ${(st.progress && st.progress.message) || st.state}`);
    await new Promise(ok => setTimeout(ok, 1000));
    if (engineSeen.sent > since) { st = engineSeen.state; since = engineSeen.sent; }
    else if (performance.now() - since > 30000) { say(`the station has not answered for 30 s; protocol run ${j.run_id} may still be running`, 'bad'); return null; }
  }
  $('rstop').hidden = true;
  const run = await (await send(`/api/runs/${j.run_id}`)).json();
  const ids = (run.result && run.result.run_ids) || [];
  if (run.status !== 'finished' || ids.length < 2) {
    say(`protocol run ${j.run_id} ended ${run.status}${st.fault ? ' (' + st.fault + ')' : ''} with ${ids.length} complete experiment log(s); ` +
      'its runs can still be diagnosed from "Stored runs"', 'bad');
    return null;
  }
  return ids;
}
// pair NAME.csv with NAME.json, post each pair to /api/runs; null (and a message) on the first refusal
async function upload(files) {
  const byStem = {};
  for (const f of files) {
    const m = f.name.match(/^(.*)\.(csv|json)$/i);
    if (m) (byStem[m[1]] = byStem[m[1]] || {})[m[2].toLowerCase()] = f;
  }
  const stems = Object.keys(byStem).sort();
  const lone = stems.filter(s => !byStem[s].csv || !byStem[s].json);
  if (!stems.length || lone.length) {
    say(stems.length ? `${lone[0]}: needs both ${lone[0]}.csv and ${lone[0]}.json` : 'pick the log files first', 'bad');
    return null;
  }
  const ids = [];
  for (const [i, stem] of stems.entries()) {
    say(`uploading ${stem} (${i + 1} of ${stems.length})…`);
    let meta;
    try { meta = JSON.parse(await byStem[stem].json.text()); } catch (e) { say(`${stem}.json: not valid JSON`, 'bad'); return null; }
    const r = await send('/api/runs', {method: 'POST', headers: {'content-type': 'application/json'},
      body: JSON.stringify({name: stem, meta, csv: await byStem[stem].csv.text()})});
    if (!r.ok) { say(`${stem}: ` + await refusal(r), 'bad'); return null; }
    ids.push((await r.json()).id);
  }
  return ids;
}
async function poll(id) {
  const res = await fetch(`/api/runs/${id}`, {headers: authHeaders()}).catch(() => null);
  if (!res || !res.ok) { say(`run ${id}: ${res ? await refusal(res) : 'the station does not answer'}`, 'bad'); return; }
  const r = await res.json();
  if (r.kind !== 'diagnosis') { say(`run ${id} is a ${r.kind} run, not a diagnosis`, 'bad'); return; }
  const stopBtn = $('dstop');
  if (r.status === 'running') {
    // what the job says it is doing (the protocol's experiment, the baseline, candidate k of n, …)
    const stopping = !stopBtn.hidden && stopBtn.disabled;  // "stopping …" stays until it has
    if (r.progress && !stopping) say(`diagnosis ${id} running: ${r.progress}…`);
    if (stopBtn.hidden) {
      stopBtn.hidden = false; stopBtn.disabled = false;
      stopBtn.onclick = async () => {
        stopBtn.disabled = true;
        say(`stopping diagnosis ${id}…`);
        const s = await fetch(`/api/diagnoses/${id}/stop`, {method: 'POST', headers: authHeaders()}).catch(() => null);
        if (s && !s.ok) say(await refusal(s), 'bad');  // it may have ended meanwhile: the next poll says how
      };
    }
    setTimeout(() => poll(id), 1500);
    return;
  }
  stopBtn.hidden = true;
  await protocolTable;  // the effect checkboxes and range rows come with it
  fillForm(r.spec || {});
  if (r.status === 'cancelled') { say(`diagnosis ${id} stopped: ${(r.result || {}).error || 'cancelled'}`, 'bad'); return; }
  if (r.status !== 'complete') { say(`diagnosis ${id} failed: ${(r.result || {}).error || r.status}`, 'bad'); return; }
  say(`diagnosis ${id} complete (stored as run ${id})`, 'ok');
  show(r.result);
  loadTraces(id, r.result);
  // the report as the API stores it (strict JSON), for scripts and notebooks
  const dl = $('download');
  if (dl.href) URL.revokeObjectURL(dl.href);
  dl.href = URL.createObjectURL(new Blob([JSON.stringify(r.result, null, 1)], {type: 'application/json'}));
  dl.download = `diagnosis-${id}.json`;
  dl.hidden = false;
}
// the form as the diagnosis shown was asked for, so that what the page says it ran is what it ran, and
// a change of one setting runs the same diagnosis otherwise (a stored report had shown the defaults)
function fillForm(spec) {
  const p = spec.protocol;
  if (p) {
    $('src').value = 'protocol';
    document.querySelectorAll('#effects input').forEach(c => { c.checked = (p.effects || []).includes(c.value); });
    for (const [id, v] of [['mag', p.magnitude], ['perr', p.param_error], ['errs', p.errors], ['seed', p.seed], ['scale', p.scale]]) {
      if (v !== undefined && v !== null) $(id).value = v;
    }
    $('scale').dispatchEvent(new Event('input'));
  } else if (spec.run_ids) {
    $('src').value = 'runs';
    $('runids').value = spec.run_ids.join(', ');
  }
  $('src').onchange();
  document.querySelectorAll('#range-rows input').forEach(i => { i.value = ''; });
  for (const [name, ends] of Object.entries(spec.bounds || {})) {
    rangeInputs(name).forEach((e, k) => { if (e) e.value = ends[k]; });
  }
  if (spec.bounds && Object.keys(spec.bounds).length) $('ranges').open = true;
  document.querySelectorAll('#tried-effects input').forEach(c => { c.checked = !spec.effects || spec.effects.includes(c.value); });
  if (spec.effects) $('tried').open = true;
}
// a diagnosis asked to try fewer candidates ("effects") says which were left out: it could not name them
function triedOnly(ranking) {
  const all = [...document.querySelectorAll('#tried-effects input')].map(c => c.value), tried = ranking.map(r => r.effect);
  const out = all.filter(e => !tried.includes(e));
  if (!tried.length || !out.length || out.length === all.length) return '';
  return `Tried only ${tried.join(', ')}, as asked: ${out.join(', ')} ${out.length === 1 ? 'was' : 'were'} left out, ` +
    `so the verdict cannot name ${out.length === 1 ? 'it' : 'them'}.`;
}
// logs with skipped or uneven samples (the replays put them on a uniform grid and leave what it made up unscored)
function irregular(logs) {
  const names = Object.keys(logs);
  if (!names.length) return '';
  return ' Sampled unevenly: ' + names.map(n =>
    `${n} (${logs[n].irregular_intervals} interval${logs[n].irregular_intervals === 1 ? '' : 's'} off the median, the longest ${(1000 * logs[n].largest_interval_s).toFixed(0)} ms)`).join(', ') +
    '; replayed on their own clock, samples missing from a log not scored.';
}
// channels that read one value throughout a log: a sensor reading nothing bends the fit to match it
function flat(logs) {
  const names = Object.keys(logs);
  if (!names.length) return '';
  return ' Read one value throughout (fine where the quantity did not change, a clamped handle or an ideal supply; a sensor reading nothing bends the fit to match it): ' + names.map(n =>
    `${n} (${Object.entries(logs[n]).map(([c, v]) => `${c} = ${fmt(v)}`).join(', ')})`).join(', ') + '.';
}
// an effect weighed against a baseline of another form that could close the same gap (a sensor
// offset against friction that differs per direction): said when the logs favour it, cannot tell, or
// find both
function alternatives(alts) {
  return alts.filter(a => a.confusable || a.better || a.also).map(a => {
    if (a.also && !a.confusable && !a.better)
      return `Beside ${a.instead_of}: ${a.explanation} (${a.description}) adds significantly to it; fitted together, ` +
        Object.entries(a.beside_effect.params).map(([k, v]) => `${k} = ${fmt(v)}`).join(', ') + '. ';
    const gc = `gap closure ${fmt(a.gap_closure)} against ${fmt(a.effect_gap_closure)} for ${a.instead_of}`;
    const what = a.dropped ? `${a.instead_of} is not the verdict: ${a.explanation} (${a.description}) closes more of the gap, and ${a.instead_of} adds nothing significant beside it`
      : a.better ? `${a.explanation} (${a.description}) closes more of the gap than ${a.instead_of}, which still adds significantly beside it`
      : `Or ${a.explanation} (${a.description}) instead of ${a.instead_of}: these logs cannot tell them apart`;
    return `${what} (${gc}). To tell: ${a.separate_by}. `;
  }).join('');
}
// a candidate's fit whose values closed the gap with its effect taken out (or left off): the
// reference was beatable; reports stored before rebased_gap_closure existed knew only the latter
function beaten(b) {
  return b ? ((b.switched_off ?? true) ? `${b.by}'s fit left the effect switched off and still closed ${fmt(b.gap_closure)} of the gap` : `${b.by}'s fit, with the effect taken out, still closes ${fmt(b.rebased_gap_closure)} of the gap`) + ": the baseline's own parameters, refitted beside it, did; " +
    (b.rereferenced ? 'the baseline was recalibrated from there and every candidate judged against that. ' : 'a descent of the baseline from there was no cheaper on the calibration logs, so part of the gap may lie in values the calibration and held-out logs see differently (drift, or a regime only one of them visits). ') : '';
}
// candidates the held-out logs cannot show: "not significant" there is not "absent"
function untested(names, unshown) {
  return names.length ? ` Not ruled out, since no held-out log shows them: ` +
    names.map(n => `${n} (needs ${unshown[n].needs.join(' or ')}` +
      (unshown[n].experiments.length ? `: run ${unshown[n].experiments.join(' or ')})` : ')')).join('; ') + '.' : '';
}
// a recalibrated value past any tolerance that the verdict does not account for: said beside the verdict
function standingIn(rc) {
  const n = (rc && rc.unaccounted) || [], m = Object.fromEntries(((rc && rc.params) || []).map(p => [p.name, p.meaning || p.name]));
  return n.length ? `The baseline is standing in for something: the recalibration moved ${n.map(x => m[x] || x).join(', ')} further than a tolerance explains (see Recalibration, below). ` : '';
}
function show(rep) {
  const v = rep.verdict;
  // what "after" holds: the verdict's effects, or with an alternative fitted beside or instead of them
  const model = rep.how_far.model || v.effects, withModel = model.length ? ` with ${model.join(' + ')}` : '';
  $('verdict').textContent = v.effects.length ? v.effects.join(' + ') : 'no significant effect';
  $('verdict-meaning').textContent = v.effects.filter(e => meaning[e]).map(e => `${e}: ${meaning[e]}.`).join(' ');
  // with no effect named: nothing above the noise to explain, or a gap that no candidate closes
  const gap = rep.baseline.gap, none = !v.effects.length && !(rep.alternatives || []).some(a => a.dropped);
  const left = none && gap && !gap.above_noise
    ? `The baseline is not significantly above the noise: E ${fmt(gap.e)} against a floor of ${fmt(gap.e_floor)} (90 % CI of the difference ${fmt(gap.ci90[0])} … ${fmt(gap.ci90[1])}); more or longer held-out logs would tell a small gap from none. `
    : (none ? 'No candidate closes what the baseline leaves. ' : '') +
      `Gap left unexplained${withModel}: ${Math.round(100 * rep.how_far.unexplained_share)} %. `;
  // fewer than 100 settled fills decide nothing about which chamber is which (run.CONVENTION_MIN_SAMPLES)
  const orderKnown = (rep.experiments.pressure_order || {}).samples >= 100;
  // one finding per line: a run-on paragraph hid the qualifiers a researcher must weigh the verdict by
  const findings = [
    v.confusable_with.length ? `Confusable with ${v.confusable_with.join(', ')}; to separate them run: ` +
      v.separating_experiments.map(s => s.experiments.join(', ')).join('; ') + '.' : '',
    alternatives(rep.alternatives || []), left, standingIn(rep.baseline.recalibration), beaten(v.baseline_beaten),
    `Held out: ${rep.experiments.held_out.join(', ')}${rep.experiments.split ? ` (${rep.experiments.split})` : ''}.`,
    triedOnly(rep.ranking),
    untested(v.untested || [], rep.experiments.unshown || {}),
    ...Object.entries(rep.experiments.dcv_wiring || {}).filter(([, w]) => w.mirrored).map(([s, w]) => `DCV-${s}'s command was read mirrored about 5 V: fully open, chamber ${s} stood near the atmosphere where the format's wiring fills it and near its regulator's pressure where it exhausts it, in ${Math.round(100 * (1 - w.agreement))} % of ${w.samples} settled samples.`),
    (rep.experiments.pressure_order || {}).swapped ? `p_a and p_b were read swapped: with both chambers filling from regulators set at least 0.5 V apart, their pressures stood in the other order in ${Math.round(100 * (1 - rep.experiments.pressure_order.agreement))} % of ${rep.experiments.pressure_order.samples} settled samples.` : '',
    (rep.experiments.torque_sign || {}).reversed ? `The torque was read with its sign reversed: it opposed the sign the chamber pressures give it in ${Math.round(100 * (1 - rep.experiments.torque_sign.agreement))} % of ${rep.experiments.torque_sign.samples} samples where they alone set it (the torque on the user rather than the user's on the handle?${orderKnown ? '' : '; if its sign is right, p_a and p_b are swapped'}).` : '',
    (rep.experiments.angle_sign || {}).reversed ? `The angle and speed were read with their signs reversed: as written, the chambers' and the measured torque fed the vane's motion power back instead of losing it to friction (net ${fmt(rep.experiments.angle_sign.dissipation)} of the power over ${rep.experiments.angle_sign.samples} samples in motion)${orderKnown || !(rep.experiments.torque_sign || {}).reversed ? '' : "; with the torque reversed too, this is also what p_a and p_b written in each other's columns look like, which no settled fill at two pressures in these logs can tell"}.` : '',
    Object.keys(rep.experiments.unmeasured_channels || {}).length ? 'Not measured: ' +
      Object.entries(rep.experiments.unmeasured_channels).map(([c, x]) => `${c} (reads ${fmt(x)} in every log)`).join(', ') +
      '; taken as a sensor the rig lacks, left out of every fit and of E.' : '',
    (rep.experiments.unscored_channels || []).length ? `Not scored: ${rep.experiments.unscored_channels.join(', ')} (no held-out sample could be, e.g. a handle resting on an end stop throughout); left out of every fit and of E.` : '',
    irregular(rep.experiments.irregular_sampling || {}), flat(rep.experiments.flat_channels || {}),
    (rep.experiments.atmosphere || {}).note ? rep.experiments.atmosphere.note.replace(/^./, c => c.toUpperCase()) + '.' : '',
  ].map(t => t.trim()).filter(Boolean);
  const list = document.createElement('ul');
  for (const t of findings) list.appendChild(document.createElement('li')).textContent = t;
  $('detail').replaceChildren(list);
  // each channel's error as a multiple of its own noise floor (1 = nothing left to explain)
  const ch = Object.keys(rep.how_far.before), W = $('howfar').clientWidth || 600, H = 220, pad = 30;
  const fl = c => rep.noise_floor.nrmse[c] || 1e-12;
  const vals = ch.flatMap(c => [rep.how_far.before[c] / fl(c), rep.how_far.after[c] / fl(c), 1]);
  const top = Math.max(...vals) * 1.1, bw = (W - 2 * pad) / ch.length;
  const colours = ['#b3261e', '#0a7d32'], names = ['before', `after${withModel}`];
  const y = v => H - pad - (H - 2 * pad) * v / top;
  let svg = '';
  ch.forEach((c, i) => {
    [rep.how_far.before[c], rep.how_far.after[c]].forEach((v, k) => {
      const r = v / fl(c), x = pad + i * bw + 12 + k * (bw - 24) / 2;
      svg += `<rect x="${x}" y="${y(r)}" width="${(bw - 24) / 2 - 3}" height="${H - pad - y(r)}" fill="${colours[k]}"><title>${c} ${names[k]}: NRMSE ${fmt(v)} = ${fmt(r)} × floor</title></rect>`;
      svg += `<text x="${x + (bw - 24) / 4}" y="${y(r) - 3}" text-anchor="middle">${fmt(r)}</text>`;
    });
    svg += `<text x="${pad + i * bw + bw / 2}" y="${H - 10}" text-anchor="middle">${c}</text>`;
  });
  svg += `<line x1="${pad}" x2="${W - pad}" y1="${y(1)}" y2="${y(1)}" stroke="#7a8794" stroke-dasharray="4 3"/>`;
  $('howfar').innerHTML = svg;
  // in HTML, not in the SVG: a model's name ("after with sensor_bias + friction_per_direction")
  // has no fixed width, and fixed slots let it run into the next entry
  const legend = $('howfar-legend');
  legend.replaceChildren(...names.map((n, k) => legendItem('■', colours[k], n)), legendItem('┄┄', '#7a8794', 'noise floor (1×)'));
  $('ranking').innerHTML = '<tr><th>Effect</th><th>GC</th><th>GC 90 % CI</th><th title="what the baseline values its fit refitted beside the effect close with the effect taken out (— when it refitted none)">GC without the effect</th><th>ΔBIC</th><th>Significant</th><th>Parameters</th></tr>' +
    rep.ranking.map(c => `<tr class="${c.significant ? 'sig' : ''}"><td>${esc(c.effect)}${meaning[c.effect] ? `<br><small class="why">${esc(meaning[c.effect])}</small>` : ''}</td><td>${fmt(c.gap_closure)}</td>` +
      `<td>${fmt(c.gap_closure_ci90[0])} … ${fmt(c.gap_closure_ci90[1])}</td><td>${fmt(c.rebased_gap_closure)}</td><td>${fmt(c.delta_bic)}</td><td>${c.significant ? 'yes' : 'no'}${c.dropped_for ? ` (not the verdict: ${c.dropped_for.join(', ')} explains more)` : ''}${!c.significant && (c.not_significant_because || []).length ? ` <small class="why">(${esc(c.not_significant_because.join("; "))})</small>` : c.switched_off ? ' (its fit left it switched off)' : ''}</td>` +
      `<td>${Object.entries(c.params).map(([k, v]) => `${k.split('.')[1]} = ${fmt(v)}`).join(', ')}</td></tr>`).join('');
  const regimes = [...new Set(rep.where.flatMap(w => Object.keys(w.regimes)))];
  // the input the residual follows most (a significant correlation only): an error that follows a command
  // a fixed time later points at what that command drives
  const follows = w => {
    const xs = Object.entries(w.input_xcorr || {}).filter(([, x]) => x.significant).sort((a, b) => b[1].max_abs - a[1].max_abs);
    if (!xs.length) return '—';
    const [name, x] = xs[0];
    const lag = typeof x.lag_s === 'number' ? `${Math.round(1000 * x.lag_s)} ms` : `${x.lag_samples} samples`;
    const all = xs.map(([n, y]) => `${n} ${fmt(y.max_abs)}`).join(', ');
    return `<span style="white-space:nowrap" title="|r| of each input past the test: ${esc(all)}">${esc(name)} ${fmt(x.max_abs)}</span>` +
      `<br><small class="why">${lag} later</small>`;
  };
  $('where').innerHTML = `<tr><th>Channel</th><th>RMS</th><th title="the RMS the sensor's noise alone leaves a right model (at standstill the torque's cancels)">noise floor</th><th>Ljung–Box p</th><th title="the input the residual correlates with most, and how much later (|r| over lags 0–49 scored samples)">follows input</th>${regimes.map(r => `<th>${r}</th>`).join('')}</tr>` +
    rep.where.map(w => `<tr><td>${w.channel}</td><td>${fmt(w.rms)}</td><td>${fmt(w.floor ?? w.noise)}</td><td>${fmt(w.ljung_box_p)}</td><td>${follows(w)}</td>` +
      regimes.map(r => `<td>${w.regimes[r] ? fmt(w.regimes[r].rms) : '—'}</td>`).join('') + '</tr>').join('');
  const logs = [...new Set(rep.where.flatMap(w => Object.keys(w.experiments || {})))];
  $('where-logs').innerHTML = `<tr><th>Log</th>${rep.where.map(w => `<th>${w.channel}</th>`).join('')}</tr>` +
    logs.map(n => `<tr><td>${esc(n)}</td>` + rep.where.map(w => {
      const e = (w.experiments || {})[n];
      return `<td>${e ? `${fmt(e.rms)} <small class="why">(${Math.round(100 * e.share)} %)</small>` : '—'}</td>`;
    }).join('') + '</tr>').join('');
  // what the recalibration made of each nominal value: one moved past any tolerance is standing in for something
  const rc = rep.baseline.recalibration || { params: [], note: null };
  $('recal-note').textContent = rc.note ? rc.note.charAt(0).toUpperCase() + rc.note.slice(1) + '.' :
    (rc.params.length ? 'No nominal value moved further than a tolerance explains.' : '');
  $('recal-note').className = rc.note ? 'msg bad' : 'msg';
  const last = v.effects[v.effects.length - 1], inModel = last && rc.params.some(p => p.in_model !== null && p.in_model !== p.value);
  $('recal').innerHTML = rc.params.length ? `<tr><th>Parameter</th><th>fitted</th><th>nominal</th><th>range</th>${inModel ? `<th>with ${esc(last)}</th>` : ''}</tr>` +
    rc.params.map(p => `<tr class="${p.far ? 'far' : ''}"><td title="${esc(p.name)}">${esc(p.meaning || p.name)}</td><td>${fmt(p.value)}${p.at_bound ? ' (end of range)' : ''}</td>` +
      `<td>${fmt(p.nominal)}</td><td>${fmt(p.range[0])} … ${fmt(p.range[1])}</td>${inModel ? `<td class="${p.in_model_far ? 'far' : ''}" title="${p.in_model_far ? 'past what a tolerance explains here too' : ''}">${fmt(p.in_model)}</td>` : ''}</tr>`).join('') : '';
}

// where in time: a held-out log's channel as measured, beside the baseline's and the verdict model's
// predictions (GET /api/diagnoses/{id}/traces); it opens on the log and channel holding most of the gap
let traces = null, traceFloor = {};
async function loadTraces(id, rep) {
  traces = null;
  traceFloor = Object.fromEntries(rep.where.map(w => [w.channel, w.floor ?? w.noise]));
  $('trace-box').hidden = true;
  $('trace-msg').textContent = '';
  const r = await fetch(`/api/diagnoses/${id}/traces`, {headers: authHeaders()}).catch(() => null);
  if (!r || !r.ok) { $('trace-msg').textContent = r ? await refusal(r) : 'the station does not answer'; return; }
  traces = await r.json();
  if (!traces.logs.length) return;
  $('trace-log').innerHTML = traces.logs.map((lg, i) => `<option value="${i}">${esc(lg.log)}</option>`).join('');
  $('trace-ch').innerHTML = Object.keys(traces.logs[0].channels).map(c => `<option>${esc(c)}</option>`).join('');
  // the channel furthest above its floor, and the log with the largest share of its error
  const worst = [...rep.where].sort((a, b) => b.rms / (b.floor || b.noise || 1) - a.rms / (a.floor || a.noise || 1))[0];
  if (worst && worst.channel in traces.logs[0].channels) {
    $('trace-ch').value = worst.channel;
    const top = Object.entries(worst.experiments || {}).sort((a, b) => b[1].share - a[1].share)[0];
    const k = top ? traces.logs.findIndex(lg => lg.log === top[0]) : -1;
    if (k >= 0) $('trace-log').value = String(k);
  }
  $('trace-box').hidden = false;
  drawTrace();
}
$('trace-log').onchange = $('trace-ch').onchange = $('trace-view').onchange = () => drawTrace();
function drawTrace() {
  if (!traces) return;
  const lg = traces.logs[+$('trace-log').value], ch = $('trace-ch').value, s = lg.channels[ch];
  const model = traces.model.length ? `after, with ${traces.model.join(' + ')}` : null;
  const residual = $('trace-view').value === 'residual', floor = traceFloor[ch];
  const minus = ys => ys.map((v, i) => v === null || s.measured[i] === null ? null : v - s.measured[i]);
  // values: the measurement a wide grey band underneath, so that a prediction agreeing with it runs inside
  // the band; residuals: each prediction's error, against the band the sensor's noise alone leaves (±floor)
  // an effect the verdict cannot tell from its own, dashed: where in time the two differ, if anywhere
  const ALIKE = ['#1f77b4', '#9467bd', '#ff7f0e'];
  const alike = Object.entries(s.confusable || {}).map(([e, ys], k) =>
    [`with ${e} alone (confusable)`, residual ? minus(ys) : ys, ALIKE[k % ALIKE.length], 1.3, '5 3']);
  const series = [...(residual ? [] : [['measured', s.measured, '#9aa4ae', 4]]),
                  ['baseline', residual ? minus(s.baseline) : s.baseline, '#b3261e', 1.3],
                  ...(s.after && model ? [[model, residual ? minus(s.after) : s.after, '#0a7d32', 1.3]] : []),
                  ...alike];
  const svg = $('trace'), W = svg.clientWidth || 600, H = 240, l = 52, r = 10, top = 10, bot = 30;
  const ts = lg.t.filter(v => v !== null), vs = series.flatMap(x => x[1]).filter(v => v !== null);
  if (residual && floor) vs.push(-floor, floor);
  if (ts.length < 2 || !vs.length) { svg.innerHTML = ''; return; }
  let lo = Math.min(...vs), hi = Math.max(...vs);
  const pad = (hi - lo) * 0.06 || Math.abs(hi) * 0.01 || 1;
  lo -= pad; hi += pad;
  const t0 = ts[0], t1 = ts[ts.length - 1];
  const X = t => l + (W - l - r) * (t - t0) / (t1 - t0), Y = v => top + (H - top - bot) * (hi - v) / (hi - lo);
  const yt = niceTicks(lo, hi, 4), xt = niceTicks(t0, t1, 6);
  let out = yt.ticks.map(v => `<line x1="${l}" x2="${W - r}" y1="${Y(v)}" y2="${Y(v)}" stroke="#e3e7ec"/>` +
    `<text x="${l - 4}" y="${Y(v) + 4}" text-anchor="end">${tickLabel(v, yt.digits)}</text>`).join('');
  out += xt.ticks.map(t => `<text x="${X(t)}" y="${H - bot + 14}" text-anchor="middle">${tickLabel(t, xt.digits)}</text>`).join('');
  if (residual && floor) {
    out += `<rect x="${l}" y="${Y(floor)}" width="${W - l - r}" height="${Y(-floor) - Y(floor)}" fill="#9aa4ae" opacity="0.3"><title>± the noise floor (${fmt(floor)})</title></rect>`;
  }
  out += `<text x="${W - r}" y="${H - 2}" text-anchor="end">t [s from the log's start]</text>`;
  const UNIT = {p_a: 'bar abs', p_b: 'bar abs', p_s: 'bar abs', p: 'bar abs', torque: 'N·m', force: 'N'};
  const unit = residual ? (UNIT[ch] || '').replace(' abs', '') : UNIT[ch];
  out += `<text x="${l + 4}" y="${top + 10}">${residual ? 'prediction − measured, ' : ''}${esc(ch)}${unit ? ` [${unit}]` : ''}</text>`;
  // a block no sample of the channel scores (null) breaks its line
  for (const [, ys, colour, width, dash] of series) {
    let d = '', pen = false;
    ys.forEach((v, i) => {
      if (v === null || lg.t[i] === null) { pen = false; return; }
      d += `${pen ? 'L' : 'M'}${X(lg.t[i]).toFixed(1)} ${Y(v).toFixed(1)} `;
      pen = true;
    });
    out += `<path d="${d}" fill="none" stroke="${colour}" stroke-width="${width}" stroke-linejoin="round"${dash ? ` stroke-dasharray="${dash}"` : ''}/>`;
  }
  svg.innerHTML = out;
  svg.dataset.series = series.length;
  const band = residual && floor ? [['▬', '#9aa4ae', '± noise floor']] : [];
  $('trace-legend').replaceChildren(...[...series.map(([name, , colour, , dash]) => [name === 'measured' ? '▬' : dash ? '┄┄' : '—', colour, name]),
    ...band].map(([key, colour, text]) => legendItem(key, colour, text)));
}
