// Sends console errors and uncaught exceptions to the local server (/api/report), so headless tests see them.
(function () {
  function report(kind, message) {
    try {
      fetch('/api/report', { method: 'POST', headers: { 'Content-Type': 'application/json' },
        body: JSON.stringify({ kind: kind, message: String(message).slice(0, 2000) }) });
    } catch (e) { /* the page still works without the server's log */ }
  }
  window.trisplatReport = function (obj) {
    fetch('/api/report', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(obj) });
  };
  const consoleError = console.error.bind(console);
  console.error = function (...args) { report('error', args.join(' ')); consoleError(...args); };
  window.addEventListener('error', (e) => report('error', (e.message || 'error') + ' at ' + (e.filename || '') + ':' + (e.lineno || '')));
  window.addEventListener('unhandledrejection', (e) => report('error', 'unhandled rejection: ' + (e.reason && e.reason.stack || e.reason)));
})();
// ?hold=1 (headless screenshots): an image the server answers only once the page has reported 'ready' or an error,
// so the page's load event, and headless Chromium's virtual time, wait for the mesh however long it takes to load.
if (new URLSearchParams(window.location.search).get('hold') === '1') {
  document.write('<img src="/api/hold" alt="" style="display:none">');
}
