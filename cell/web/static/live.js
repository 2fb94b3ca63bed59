// The live view of one job: polls /api/jobs/ID once a second and updates the page.
(function () {
  const root = document.getElementById('live');
  const id = root.dataset.job;
  const $ = x => document.getElementById(x);
  const show = (el, on) => { if (el) el.hidden = !on; };
  let lastImage = null, timer = null;
  function robot(doc) {
    const p = doc.flange_xyz_m || [];
    if (!window.Plotly || !p.length) return;
    const part = doc.part_xyz_m ? [{x: [doc.part_xyz_m[0]], y: [doc.part_xyz_m[1]], mode: 'markers+text', text: ['part'],
      textposition: 'bottom center', marker: {size: 22, color: '#9aa5b1', symbol: 'diamond'}, name: 'part'}] : [];
    Plotly.react('robot', [...part,
      {x: [0], y: [0], mode: 'markers+text', text: ['robot base'], textposition: 'top center', marker: {size: 14, color: '#555', symbol: 'square'}, name: 'base'},
      {x: p.map(q => q[0]), y: p.map(q => q[1]), mode: 'lines+markers', name: 'stations', line: {color: '#bbb'}, marker: {size: 5, color: '#0969da'}},
      {x: [p[p.length - 1][0]], y: [p[p.length - 1][1]], mode: 'markers', name: 'camera now', marker: {size: 14, color: '#cf222e'}}],
      {margin: {t: 10, l: 40, r: 10, b: 30}, showlegend: false, xaxis: {title: 'x [m]'}, yaxis: {title: 'y [m]', scaleanchor: 'x'}});
  }
  async function poll() {
    let doc;
    try {
      const r = await fetch('/api/jobs/' + encodeURIComponent(id), {headers: {'Accept': 'application/json'}});
      if (r.status === 401) { location.href = '/login'; return; }
      if (!r.ok) return;
      doc = await r.json();
    } catch (e) { return; }
    $('state').textContent = doc.state + (doc.stage && doc.stage !== doc.state ? ' (' + doc.stage + ')' : '');
    const pct = Math.round(doc.progress * 1000) / 10;
    $('bar').style.width = pct + '%';
    $('progress').textContent = Math.round(pct) + ' %' + (doc.stations ? `, ${doc.stations_done} of ${doc.stations} images` : '');
    $('timeleft').textContent = doc.time_left_s ? `about ${Math.ceil(doc.time_left_s)} s left` : '';
    $('log').textContent = (doc.log || []).join('\n');
    if (doc.latest_image && doc.latest_image + doc.state !== lastImage) {
      lastImage = doc.latest_image + doc.state;
      $('image').src = '/jobs/' + encodeURIComponent(id) + '/image.jpg?' + Date.now();
      $('imgcaption').textContent = doc.latest_image;
    }
    robot(doc);
    const ended = ['DONE', 'FAULTED', 'ABORTED'].includes(doc.state) && !doc.running;
    show($('abortform'), doc.running);
    show($('resumeform'), ended && doc.state !== 'DONE' && doc.kept !== false);
    show($('ackform'), ended && doc.state === 'FAULTED');
    show($('signform'), doc.state === 'DONE');
    ['reportlink', 'pdflink', 'csvlink', 'qiflink', 'nextpart'].forEach(k => show($(k), doc.state === 'DONE'));
    show($('fault'), !!doc.advice); if (doc.advice) $('fault').textContent = doc.advice;
    if (doc.verdict) { const v = $('verdict'); v.textContent = doc.verdict; v.className = 'verdict ' + doc.verdict; show(v, true); }
    root.dataset.state = doc.state;
    if (ended && timer) { clearInterval(timer); timer = null; }
  }
  poll();
  timer = setInterval(poll, 1000);
})();
