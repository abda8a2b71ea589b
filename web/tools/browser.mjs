#!/usr/bin/env node
// Headless-browser driver of the springtime web export (no npm dependencies; node ≥ 18).
//
//   node web/tools/browser.mjs PAGE [SCENARIO] [--browser PATH] [--timeout SECONDS]
//
// PAGE: an exported folder or its index.html. SCENARIO: a JSON file, `-` for stdin, or inline
// JSON (`{"steps": [...]}`); default: `{"steps": [{"op": "info"}]}`. Launches Chromium (or
// Chrome) headless with networking disabled, talks to it over the DevTools protocol on a pipe
// (--remote-debugging-pipe: no port, no WebSocket), opens file://PAGE, waits for
// `springtime.ready`, runs the steps and prints one JSON object on stdout:
//
//   {"ok": true, "browser": "...", "page": "file:///...", "ready_ms": 412, "info": {...},
//    "results": [{"op": "reset"}, {"op": "step", "frames": 100, "finite": true, "ms": 21.5},
//                {"op": "positions", "positions": [x0, y0, z0, ...]}, ...],
//    "console_errors": [], "blocked_requests": []}
//
// or {"ok": false, "error": "...", ...} with exit code 1 (3: no browser found, 2: bad usage).
// Steps (`op` and its keys): reset; step {frames}; positions; velocities;
// set_state {x, v?, pinned?}; set_pinned {pinned}; pin_path {frames, particles?};
// drag {particle, to: [x, y, z]}; release {particle?}; scene {name}; bench {seconds};
// rollout {frames, every}: positions at frame 0, every `every` frames and the last;
// info; eval {expr} (awaited); wait {ms}; play; pause; screenshot {path};
// mouse {events: [{type: mousePressed|mouseMoved|mouseReleased, x, y, wait_ms?}, ...]} (CSS px;
// `springtime.screenOf(i)` gives a particle's).
// The browser: --browser, else $SPRINGTIME_BROWSER, else the first of chromium,
// chromium-browser, google-chrome, google-chrome-stable, chrome on PATH.

import { spawn } from 'node:child_process';
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { pathToFileURL } from 'node:url';

const BROWSERS = ['chromium', 'chromium-browser', 'google-chrome', 'google-chrome-stable', 'chrome'];

function out(obj, code) {
  process.stdout.write(JSON.stringify(obj) + '\n', () => process.exit(code));
}

function usage(msg) {
  out({ ok: false, error: msg + ' (usage: node web/tools/browser.mjs PAGE [SCENARIO] [--browser PATH] [--timeout SECONDS])' }, 2);
}

function parseArgs(argv) {
  const args = { positional: [], browser: null, timeout: 120 };
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    if (a === '--browser') args.browser = argv[++i];
    else if (a === '--timeout') args.timeout = Number(argv[++i]);
    else if (a === '-h' || a === '--help') args.help = true;
    else args.positional.push(a);
  }
  return args;
}

function findBrowser(explicit) {
  const cands = explicit ? [explicit] : process.env.SPRINGTIME_BROWSER ? [process.env.SPRINGTIME_BROWSER] : BROWSERS;
  for (const c of cands) {
    if (c.includes('/')) {
      if (fs.existsSync(c)) return c;
      continue;
    }
    for (const dir of (process.env.PATH || '').split(path.delimiter)) {
      const p = path.join(dir, c);
      try {
        fs.accessSync(p, fs.constants.X_OK);
        return p;
      } catch {
        // not here
      }
    }
  }
  return null;
}

function readScenario(arg) {
  if (arg == null) return { steps: [{ op: 'info' }] };
  let text;
  if (arg === '-') text = fs.readFileSync(0, 'utf8');
  else if (arg.trim().startsWith('{') || arg.trim().startsWith('[')) text = arg;
  else text = fs.readFileSync(arg, 'utf8');
  const s = JSON.parse(text);
  return Array.isArray(s) ? { steps: s } : s;
}

/** A DevTools-protocol connection over chromium's pipe (fd 3 in, fd 4 out, NUL-separated JSON). */
class Cdp {
  constructor(write, read) {
    this.write = write;
    this.next = 1;
    this.pending = new Map();
    this.listeners = [];
    let buf = '';
    read.setEncoding('utf8');
    read.on('data', (chunk) => {
      buf += chunk;
      let end;
      while ((end = buf.indexOf('\0')) >= 0) {
        const msg = JSON.parse(buf.slice(0, end));
        buf = buf.slice(end + 1);
        if (msg.id && this.pending.has(msg.id)) {
          const { resolve, reject, method } = this.pending.get(msg.id);
          this.pending.delete(msg.id);
          if (msg.error) reject(new Error(method + ': ' + msg.error.message + (msg.error.data ? ' (' + msg.error.data + ')' : '')));
          else resolve(msg.result);
        } else if (msg.method) {
          for (const l of this.listeners) l(msg);
        }
      }
    });
  }

  send(method, params, sessionId) {
    const id = this.next++;
    const msg = { id, method, params: params || {} };
    if (sessionId) msg.sessionId = sessionId;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject, method });
      this.write.write(JSON.stringify(msg) + '\0');
    });
  }

  on(fn) {
    this.listeners.push(fn);
  }

  failAll(err) {
    for (const { reject } of this.pending.values()) reject(err);
    this.pending.clear();
  }
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function expression(step) {
  const j = (v) => JSON.stringify(v);
  switch (step.op) {
    case 'reset':
      return 'springtime.reset(), null';
    case 'step':
      return `(() => { const t0 = performance.now(); const finite = springtime.step(${j(step.frames ?? 1)}); return { frames: ${j(step.frames ?? 1)}, finite, ms: performance.now() - t0 }; })()`;
    case 'positions':
      return '({ positions: springtime.positions() })';
    case 'velocities':
      return '({ velocities: springtime.velocities() })';
    case 'set_state':
      return `springtime.setState(${j(step.x)}, ${j(step.v ?? null)}, ${j(step.pinned ?? null)}), null`;
    case 'set_pinned':
      return `springtime.setPinned(${j(step.pinned)}), null`;
    case 'pin_path':
      return `springtime.setPinPath(${j(step.frames)}, ${j(step.particles ?? null)}), null`;
    case 'drag':
      return `springtime.drag(${j(step.particle)}, ${j(step.to)}), null`;
    case 'release':
      return `springtime.release(${step.particle == null ? '' : j(step.particle)}), null`;
    case 'scene':
      return `springtime.setScene(${j(step.name)}), null`;
    case 'bench':
      return `(() => { const ratio = springtime.bench(${j(step.seconds ?? 2)}); return Object.assign({ ratio }, springtime.lastBench); })()`;
    case 'rollout':
      return `(() => { const n = ${j(step.frames)}, every = ${j(step.every ?? 1)}; const frames = [0], positions = [springtime.positions()]; let finite = true;
        for (let f = 0; f < n;) { const k = Math.min(every, n - f); finite = springtime.step(k) && finite; f += k; frames.push(f); positions.push(springtime.positions()); }
        return { frames, positions, finite }; })()`;
    case 'info':
      return '({ info: springtime.info() })';
    case 'eval':
      return `(async () => ({ value: await (${step.expr}) }))()`;
    case 'play':
      return 'springtime.play(), null';
    case 'pause':
      return 'springtime.pause(), null';
    default:
      throw new Error('unknown op ' + j(step.op));
  }
}

async function main() {
  const args = parseArgs(process.argv.slice(2));
  if (args.help) return usage('help');
  if (!args.positional.length) return usage('no PAGE');
  if (!(args.timeout > 0)) return usage('--timeout must be positive');
  let page = path.resolve(args.positional[0]);
  if (fs.existsSync(page) && fs.statSync(page).isDirectory()) page = path.join(page, 'index.html');
  if (!fs.existsSync(page)) return out({ ok: false, error: 'no page at ' + page }, 1);
  let scenario;
  try {
    scenario = readScenario(args.positional[1]);
  } catch (e) {
    return usage('bad scenario: ' + e.message);
  }
  const browser = findBrowser(args.browser);
  if (!browser) {
    return out({ ok: false, error: 'no browser found: install chromium (apt-get install chromium) or pass --browser PATH / set SPRINGTIME_BROWSER; looked for ' + BROWSERS.join(', ') }, 3);
  }

  const url = pathToFileURL(page).href + (scenario.query ? '?' + scenario.query : '?autoplay=0');
  const profile = fs.mkdtempSync(path.join(os.tmpdir(), 'springtime-chrome-'));
  const flags = [
    '--headless=new',
    '--remote-debugging-pipe',
    '--user-data-dir=' + profile,
    '--no-first-run',
    '--no-default-browser-check',
    '--disable-extensions',
    '--disable-background-networking',
    '--disable-component-update',
    '--disable-sync',
    '--disable-default-apps',
    '--disable-domain-reliability',
    '--mute-audio',
    '--window-size=' + (scenario.window || '1280,800'),
    // No network: names resolve nowhere, and requests are failed below.
    '--host-resolver-rules=MAP * ~NOTFOUND',
    '--use-angle=swiftshader',
    '--enable-unsafe-swiftshader',
    '--ignore-gpu-blocklist',
  ];
  if ((process.getuid && process.getuid() === 0) || process.env.SPRINGTIME_NO_SANDBOX) flags.push('--no-sandbox');
  const child = spawn(browser, flags, { stdio: ['ignore', 'ignore', 'pipe', 'pipe', 'pipe'] });
  let stderr = '';
  child.stderr.on('data', (d) => {
    // The browser's own log, less the noise of a machine without D-Bus.
    const lines = String(d).split('\n').filter((l) => l.trim() && !/dbus|DBus/.test(l));
    if (lines.length) stderr = (stderr + lines.join('\n') + '\n').slice(-4000);
  });
  const report = { ok: false, browser: null, page: url, results: [], console_errors: [], blocked_requests: [] };
  let finished = false;
  const cleanup = () => {
    try {
      child.kill('SIGKILL');
    } catch {
      // gone
    }
    try {
      fs.rmSync(profile, { recursive: true, force: true });
    } catch {
      // best effort
    }
  };
  const finish = (code) => {
    if (finished) return;
    finished = true;
    cleanup();
    out(report, code);
  };
  const watchdog = setTimeout(() => {
    report.error = 'timed out after ' + args.timeout + ' s' + (report.results.length ? ' (after ' + report.results.length + ' steps)' : '');
    report.browser_log = stderr;
    finish(1);
  }, args.timeout * 1000);
  watchdog.unref();
  const cdp = new Cdp(child.stdio[3], child.stdio[4]);
  child.on('error', (e) => {
    report.error = 'cannot start ' + browser + ': ' + e.message;
    finish(1);
  });
  child.on('exit', (code, signal) => {
    if (finished) return;
    cdp.failAll(new Error('the browser exited (' + (code ?? signal) + ')'));
    report.error = 'the browser exited (' + (code ?? signal) + ') before the scenario finished';
    report.browser_log = stderr;
    finish(1);
  });

  try {
    const version = await cdp.send('Browser.getVersion');
    report.browser = version.product;
    const { targetId } = await cdp.send('Target.createTarget', { url: 'about:blank' });
    const { sessionId } = await cdp.send('Target.attachToTarget', { targetId, flatten: true });
    const send = (m, p) => cdp.send(m, p, sessionId);
    cdp.on((msg) => {
      if (msg.sessionId !== sessionId) return;
      if (msg.method === 'Runtime.exceptionThrown') {
        const d = msg.params.exceptionDetails;
        report.console_errors.push((d.exception && d.exception.description) || d.text);
      } else if (msg.method === 'Runtime.consoleAPICalled' && (msg.params.type === 'error' || msg.params.type === 'assert')) {
        report.console_errors.push(msg.params.args.map((a) => a.value ?? a.description ?? '').join(' '));
      } else if (msg.method === 'Log.entryAdded' && msg.params.entry.level === 'error') {
        report.console_errors.push(msg.params.entry.text + (msg.params.entry.url ? ' (' + msg.params.entry.url + ')' : ''));
      } else if (msg.method === 'Fetch.requestPaused') {
        report.blocked_requests.push(msg.params.request.url);
        send('Fetch.failRequest', { requestId: msg.params.requestId, errorReason: 'InternetDisconnected' }).catch(() => {});
      }
    });
    await send('Runtime.enable');
    await send('Log.enable');
    await send('Page.enable');
    await send('Network.enable');
    await send('Network.emulateNetworkConditions', { offline: true, latency: 0, downloadThroughput: -1, uploadThroughput: -1 });
    await send('Fetch.enable', { patterns: ['http://*', 'https://*', 'ws://*', 'wss://*', 'ftp://*'].map((urlPattern) => ({ urlPattern })) });

    const evaluate = async (expr, ms) => {
      const r = await send('Runtime.evaluate', { expression: expr, returnByValue: true, awaitPromise: true, timeout: ms });
      if (r.exceptionDetails) {
        const d = r.exceptionDetails;
        throw new Error((d.exception && d.exception.description) || d.text);
      }
      return r.result.value;
    };

    const t0 = Date.now();
    const nav = await send('Page.navigate', { url });
    if (nav.errorText) throw new Error('cannot open ' + url + ': ' + nav.errorText);
    const readyBy = t0 + 1000 * Math.min(args.timeout, scenario.ready_timeout_s || 60);
    for (;;) {
      let s = null;
      try {
        s = await evaluate('window.springtime ? { ready: !!springtime.ready, error: springtime.error || null } : null', 5000);
      } catch {
        // the page is still loading
      }
      if (s && s.error) throw new Error('the page failed: ' + s.error);
      if (s && s.ready) break;
      if (Date.now() > readyBy) throw new Error('springtime.ready did not turn true within ' + Math.round((readyBy - t0) / 1000) + ' s');
      await sleep(50);
    }
    report.ready_ms = Date.now() - t0;
    report.info = await evaluate('springtime.info()', 10000);

    for (const step of scenario.steps || []) {
      const result = { op: step.op };
      if (step.op === 'wait') {
        await sleep(step.ms ?? 1000);
      } else if (step.op === 'mouse') {
        // Pointer input as a person gives it: [{type: mousePressed|mouseMoved|mouseReleased, x, y}, ...]
        for (const ev of step.events || []) {
          await send('Input.dispatchMouseEvent', { button: 'left', buttons: ev.type === 'mouseReleased' ? 0 : 1, clickCount: 1, ...ev });
          if (ev.wait_ms) await sleep(ev.wait_ms);
        }
      } else if (step.op === 'screenshot') {
        await evaluate('new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(() => r(null))))', 10000);
        const shot = await send('Page.captureScreenshot', { format: 'png' });
        const file = path.resolve(step.path || 'springtime.png');
        fs.writeFileSync(file, Buffer.from(shot.data, 'base64'));
        result.path = file;
      } else {
        const v = await evaluate(expression(step), 1000 * (step.timeout_s || args.timeout));
        if (v && typeof v === 'object' && !Array.isArray(v)) Object.assign(result, v);
        else if (v !== null && v !== undefined) result.value = v;
      }
      report.results.push(result);
    }
    report.ok = true;
    try {
      await cdp.send('Browser.close');
    } catch {
      // closing anyway
    }
    finish(0);
  } catch (e) {
    report.error = String(e.message || e);
    if (stderr && !report.ready_ms && !/the page failed/.test(report.error)) report.browser_log = stderr;
    finish(1);
  }
}

main();
