/* springtime web page: simulates the exported surrogate live (src/sim.js), draws it with
 * three.js (vendor/three.min.js, `window.THREE`) and exposes `window.springtime` for scripts
 * and automated checks (see web/README.md). A classic script: works from file://.
 */
(function () {
  'use strict';

  const api = { ready: false, error: null, webgl: false, lastBench: null };
  window.springtime = api;

  const params = new URLSearchParams(window.location.search);
  const $ = (id) => document.getElementById(id);

  function showMessage(html) {
    const m = $('message');
    m.innerHTML = html;
    m.hidden = false;
  }

  function fatal(msg, html) {
    api.error = msg;
    showMessage('<b>springtime:</b> ' + (html || msg));
    if (window.console) console.error('springtime: ' + msg);
  }

  // ---- colour map (viridis, 9 stops) ----
  const VIRIDIS = [
    [0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.53], [0.207, 0.372, 0.553],
    [0.164, 0.471, 0.558], [0.128, 0.567, 0.551], [0.135, 0.659, 0.518], [0.267, 0.749, 0.441],
    [0.478, 0.821, 0.318], [0.741, 0.873, 0.15], [0.993, 0.906, 0.144],
  ];
  function colormap(t, out) {
    const u = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (VIRIDIS.length - 1);
    const i = Math.min(VIRIDIS.length - 2, Math.floor(u));
    const f = u - i;
    for (let c = 0; c < 3; c++) out[c] = VIRIDIS[i][c] * (1 - f) + VIRIDIS[i + 1][c] * f;
    return out;
  }
  function fmt(x, digits) {
    if (!Number.isFinite(x)) return String(x);
    const a = Math.abs(x);
    if (a !== 0 && (a < 1e-3 || a >= 1e5)) return x.toExponential(digits == null ? 2 : digits);
    return x.toFixed(digits == null ? 3 : digits).replace(/\.?0+$/, '') || '0';
  }

  function start(json) {
    const Sim = window.SpringtimeSim;
    if (!Sim) return fatal('src/sim.js did not load.');
    let cloth;
    try {
      cloth = new Sim.Cloth(json);
    } catch (e) {
      return fatal(String(e.message || e));
    }
    api.cloth = cloth;
    const c = cloth.constants;
    const st = cloth.getStability();
    const size = Math.max(json.width || 1, json.height || 1);
    let scene = 'pinned';
    let playing = params.get('autoplay') !== '0';
    let speed = 1;

    // ---- info ----
    const fam = Array.isArray(json.family) ? json.family : [];
    const families = Array.from(new Set(fam));
    $('info').innerHTML =
      (json.grid ? json.grid[0] + ' × ' + json.grid[1] + ' grid, ' : 'mesh, ') +
      c.particles + ' particles, ' + c.springs + ' springs' +
      (cloth.T ? ', ' + cloth.T + ' curvature elements' : '') + '<br>' +
      'frame ' + fmt(c.frameDt * 1000) + ' ms, ' + c.substeps + ' substep' + (c.substeps > 1 ? 's' : '') +
      ', particle mass ' + fmt(c.mass, 4) + ' kg<br>' +
      'stability dt²ω² + 2dtγ = ' + fmt(st.number, 3) + ' (stable below ' + st.limit + ')' +
      (json.pinned && json.pinned.length ? '<br>' + json.pinned.length + ' pinned particles' : '');
    if (!(st.number < st.limit)) $('note').textContent = 'The step is past its stability limit: the cloth may blow up.';

    // ---- springs shown and their colours ----
    const familySel = $('family');
    const famOptions = [['all', 'all']].concat(families.map((f) => [f, f]));
    for (const [v, label] of famOptions) {
      const o = document.createElement('option');
      o.value = v;
      o.textContent = label;
      familySel.appendChild(o);
    }
    if (families.includes('structural')) familySel.value = 'structural';
    let kmin = Infinity;
    let kmax = -Infinity;
    for (const k of json.k) {
      kmin = Math.min(kmin, k);
      kmax = Math.max(kmax, k);
    }
    if (!(kmax > kmin)) kmax = kmin + 1;
    $('kmin').textContent = fmt(kmin, 3);
    $('kmax').textContent = fmt(kmax, 3);
    const stops = [];
    for (let i = 0; i <= 10; i++) {
      const col = colormap(i / 10, [0, 0, 0]).map((x) => Math.round(255 * x));
      stops.push('rgb(' + col.join(',') + ') ' + i * 10 + '%');
    }
    $('bar').style.background = 'linear-gradient(to right, ' + stops.join(', ') + ')';
    const kColour = (k, out) => colormap((k - kmin) / (kmax - kmin), out);

    // ---- the scene ----
    const T = window.THREE;
    let view = null;
    try {
      if (!T) throw new Error('vendor/three.min.js did not load');
      view = makeView(T);
      api.webgl = true;
    } catch (e) {
      showMessage('No 3-D view (' + String(e.message || e) + '); the simulation still runs: see the numbers on the right.');
    }

    function makeView(T) {
      const canvas = $('view');
      const renderer = new T.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
      renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
      renderer.setSize(window.innerWidth, window.innerHeight, false);
      const sc = new T.Scene();
      sc.background = new T.Color(0x1d2025);
      const camera = new T.PerspectiveCamera(40, window.innerWidth / window.innerHeight, size * 0.01, size * 100);
      camera.up.set(0, 0, 1);
      sc.add(new T.HemisphereLight(0xdfe8ff, 0x40372e, 1.6));
      const sun = new T.DirectionalLight(0xffffff, 1.8);
      sun.position.set(size, -size, 2 * size);
      sc.add(sun);

      // The cloth: triangles coloured by the mean k of each particle's springs.
      const p = cloth.n;
      let tris = json.triangles || [];
      if (!tris.length && json.grid) {
        const [nx, ny] = json.grid;
        tris = [];
        for (let r = 0; r + 1 < ny; r++) {
          for (let q = 0; q + 1 < nx; q++) {
            const a = r * nx + q;
            tris.push([a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]);
          }
        }
      }
      const geo = new T.BufferGeometry();
      const posAttr = new T.BufferAttribute(cloth.x, 3);
      posAttr.setUsage(T.DynamicDrawUsage);
      geo.setAttribute('position', posAttr);
      const vcol = new Float32Array(3 * p);
      const geoIndex = [];
      for (const t of tris) geoIndex.push(t[0], t[1], t[2]);
      geo.setIndex(geoIndex);
      geo.setAttribute('color', new T.BufferAttribute(vcol, 3));
      const mat = new T.MeshStandardMaterial({
        vertexColors: true, side: T.DoubleSide, roughness: 0.85, metalness: 0.0,
        polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1,
      });
      const mesh = new T.Mesh(geo, mat);
      sc.add(mesh);

      // Springs as lines, each in its k's colour.
      const lineGeo = new T.BufferGeometry();
      const linePos = new Float32Array(6 * c.springs);
      const lineCol = new Float32Array(6 * c.springs);
      const linePosAttr = new T.BufferAttribute(linePos, 3);
      linePosAttr.setUsage(T.DynamicDrawUsage);
      lineGeo.setAttribute('position', linePosAttr);
      lineGeo.setAttribute('color', new T.BufferAttribute(lineCol, 3));
      const lines = new T.LineSegments(lineGeo, new T.LineBasicMaterial({ vertexColors: true }));
      sc.add(lines);
      let shown = [];

      function setFamily(which) {
        const kSum = new Float64Array(p);
        const kCount = new Float64Array(p);
        shown = [];
        for (let s = 0; s < c.springs; s++) {
          if (which !== 'all' && fam[s] !== which) continue;
          shown.push(s);
          const [a, b] = json.springs[s];
          kSum[a] += json.k[s];
          kSum[b] += json.k[s];
          kCount[a]++;
          kCount[b]++;
        }
        const col = [0, 0, 0];
        for (let i = 0; i < p; i++) {
          kColour(kCount[i] ? kSum[i] / kCount[i] : kmin, col);
          vcol[3 * i] = col[0];
          vcol[3 * i + 1] = col[1];
          vcol[3 * i + 2] = col[2];
        }
        geo.attributes.color.needsUpdate = true;
        shown.forEach((s, q) => {
          kColour(json.k[s], col);
          for (let e = 0; e < 2; e++) {
            lineCol[6 * q + 3 * e] = col[0];
            lineCol[6 * q + 3 * e + 1] = col[1];
            lineCol[6 * q + 3 * e + 2] = col[2];
          }
        });
        lineGeo.attributes.color.needsUpdate = true;
        lineGeo.setDrawRange(0, 2 * shown.length);
      }

      // Pinned particles (red) and the dragged one (yellow).
      const spacing = json.grid ? Math.min(json.width / (json.grid[0] - 1), json.height / (json.grid[1] - 1)) : size / Math.sqrt(p);
      const ball = new T.SphereGeometry(0.18 * spacing, 12, 8);
      const pinMesh = new T.InstancedMesh(ball, new T.MeshStandardMaterial({ color: 0xe0483e }), p);
      pinMesh.count = 0;
      sc.add(pinMesh);
      const dragMesh = new T.Mesh(new T.SphereGeometry(0.28 * spacing, 16, 12), new T.MeshStandardMaterial({ color: 0xffd23f }));
      dragMesh.visible = false;
      sc.add(dragMesh);

      // Colliders of the drop scenes.
      const colliderGroup = new T.Group();
      sc.add(colliderGroup);
      const colliderMat = new T.MeshStandardMaterial({ color: 0x8a94a6, roughness: 0.7 });
      const groundMat = new T.MeshStandardMaterial({ color: 0x3b4048, roughness: 1 });
      function showColliders(list) {
        while (colliderGroup.children.length) {
          const o = colliderGroup.children.pop();
          o.geometry.dispose();
        }
        for (const col of list) {
          let m;
          if (col.kind === 'sphere') {
            m = new T.Mesh(new T.SphereGeometry(col.radius, 48, 32), colliderMat);
            m.position.set(col.center[0], col.center[1], col.center[2]);
          } else if (col.kind === 'rounded_box') {
            const e = col.half.map((h) => 2 * (h + col.radius));
            m = new T.Mesh(new T.BoxGeometry(e[0], e[1], e[2]), colliderMat);
            m.position.set(col.center[0], col.center[1], col.center[2]);
          } else if (col.kind === 'plane') {
            m = new T.Mesh(new T.PlaneGeometry(6 * size, 6 * size), groundMat);
            m.position.set(0, 0, col.height);
          }
          if (m) colliderGroup.add(m);
        }
      }

      // Camera on the sheet (its rest rectangle and as far below as it can hang).
      let controls = null;
      function frameCamera() {
        const box = new T.Box3().setFromBufferAttribute(posAttr);
        const centre = box.getCenter(new T.Vector3());
        if (scene === 'pinned') centre.z -= 0.3 * size;
        else centre.z = 0;
        controls.target.copy(centre);
        camera.position.set(centre.x + 0.9 * size, centre.y - 1.9 * size, centre.z + 0.9 * size);
        controls.update();
      }

      // Dragging: the particle nearest the point of the cloth under the pointer, in the plane
      // facing the camera through it.
      const ray = new T.Raycaster();
      const ndc = new T.Vector2();
      const plane = new T.Plane();
      const hitPoint = new T.Vector3();
      let dragging = -1;
      function pointer(ev) {
        const r = canvas.getBoundingClientRect();
        ndc.set(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1);
        ray.setFromCamera(ndc, camera);
      }
      canvas.addEventListener('pointerdown', (ev) => {
        if (ev.button !== 0) return;
        pointer(ev);
        geo.computeBoundingSphere();
        const hits = ray.intersectObject(mesh, false);
        if (!hits.length || !hits[0].face) return;
        const f = hits[0].face;
        let best = -1;
        let bestD = Infinity;
        for (const i of [f.a, f.b, f.c]) {
          const d = hits[0].point.distanceToSquared(new T.Vector3(cloth.x[3 * i], cloth.x[3 * i + 1], cloth.x[3 * i + 2]));
          if (d < bestD) {
            bestD = d;
            best = i;
          }
        }
        dragging = best;
        controls.enabled = false;
        const at = new T.Vector3(cloth.x[3 * best], cloth.x[3 * best + 1], cloth.x[3 * best + 2]);
        plane.setFromNormalAndCoplanarPoint(camera.getWorldDirection(new T.Vector3()), at);
        cloth.drag(best, [at.x, at.y, at.z]);
        canvas.setPointerCapture(ev.pointerId);
      });
      canvas.addEventListener('pointermove', (ev) => {
        if (dragging < 0) return;
        pointer(ev);
        if (ray.ray.intersectPlane(plane, hitPoint)) cloth.drag(dragging, [hitPoint.x, hitPoint.y, hitPoint.z]);
      });
      const endDrag = () => {
        if (dragging < 0) return;
        cloth.release(dragging);
        dragging = -1;
        controls.enabled = true;
      };
      canvas.addEventListener('pointerup', endDrag);
      canvas.addEventListener('pointercancel', endDrag);
      // OrbitControls registers after these listeners, so a drag on the cloth disables it first.
      controls = new T.OrbitControls(camera, canvas);

      window.addEventListener('resize', () => {
        camera.aspect = window.innerWidth / window.innerHeight;
        camera.updateProjectionMatrix();
        renderer.setSize(window.innerWidth, window.innerHeight, false);
      });

      const m4 = new T.Matrix4();
      let showMode = 'both';
      function render() {
        posAttr.needsUpdate = true;
        if (showMode !== 'springs') geo.computeVertexNormals();
        mesh.visible = showMode !== 'springs';
        lines.visible = showMode !== 'surface';
        if (lines.visible) {
          const x = cloth.x;
          for (let q = 0; q < shown.length; q++) {
            const s = shown[q];
            const a = 3 * cloth.ia[s];
            const b = 3 * cloth.ib[s];
            const o = 6 * q;
            linePos[o] = x[a];
            linePos[o + 1] = x[a + 1];
            linePos[o + 2] = x[a + 2];
            linePos[o + 3] = x[b];
            linePos[o + 4] = x[b + 1];
            linePos[o + 5] = x[b + 2];
          }
          linePosAttr.needsUpdate = true;
          lineGeo.computeBoundingSphere();
        }
        let n = 0;
        for (let i = 0; i < p; i++) {
          if (!cloth.pinned[i]) continue;
          m4.makeTranslation(cloth.x[3 * i], cloth.x[3 * i + 1], cloth.x[3 * i + 2]);
          pinMesh.setMatrixAt(n++, m4);
        }
        pinMesh.count = n;
        pinMesh.instanceMatrix.needsUpdate = true;
        const d = dragging >= 0 ? dragging : cloth.drags.size ? cloth.drags.keys().next().value : -1;
        dragMesh.visible = d >= 0;
        if (d >= 0) dragMesh.position.set(cloth.x[3 * d], cloth.x[3 * d + 1], cloth.x[3 * d + 2]);
        controls.update();
        renderer.render(sc, camera);
      }

      /** Particle `i`'s position on the page, CSS pixels [x, y] (for scripted pointer input). */
      function screenOf(i) {
        const v = new T.Vector3(cloth.x[3 * i], cloth.x[3 * i + 1], cloth.x[3 * i + 2]).project(camera);
        const r = canvas.getBoundingClientRect();
        return [r.left + ((v.x + 1) / 2) * r.width, r.top + ((1 - v.y) / 2) * r.height];
      }

      return {
        render,
        screenOf,
        setFamily,
        showColliders,
        frameCamera,
        setShow(mode) {
          showMode = mode;
        },
        renderer,
      };
    }

    // ---- simulation control ----
    const stats = { frames: 0, simSeconds: 0, stepMs: 0, wallMs: 0, renders: 0, fps: 0, ratio: 0, capacity: 0 };
    let diverged = false;

    function setScene(name) {
      if (!['pinned', 'sphere', 'table'].includes(name)) throw new Error('scene must be pinned, sphere or table');
      scene = name;
      const dropped = cloth.dropOn(name === 'pinned' ? 'none' : name);
      diverged = false;
      $('scene').value = name;
      if (view) {
        view.showColliders(dropped ? dropped.colliders : []);
        view.frameCamera();
      }
      updateStats(true);
    }

    function checkFinite() {
      if (!cloth.finite()) {
        diverged = true;
        setPlaying(false);
        $('note').textContent = 'The simulation diverged (non-finite positions): press Reset.';
      }
    }

    function setPlaying(on) {
      playing = on;
      $('play').textContent = playing ? 'Pause' : 'Play';
    }

    function updateStats(force) {
      const now = performance.now();
      if (!force && now - stats.since < 500) return;
      const wall = (now - (stats.since || now)) / 1000;
      if (wall > 0) {
        stats.fps = stats.renders / wall;
        stats.ratio = stats.simSeconds / wall;
        stats.capacity = stats.stepMs > 0 ? stats.simSeconds / (stats.stepMs / 1000) : stats.capacity;
      }
      stats.since = now;
      stats.renders = 0;
      stats.simSeconds = 0;
      stats.stepMs = 0;
      $('stats').innerHTML =
        '<div class="big">t = ' + cloth.time.toFixed(3) + ' s</div>' +
        '<div>step rate: ' + fmt(stats.ratio, 2) + ' simulated s per wall s' + (playing ? '' : ' (paused)') + '</div>' +
        '<div>capacity: ' + (stats.capacity > 0 ? fmt(stats.capacity, 2) + '× real time' : '–') + '</div>' +
        '<div>frame rate: ' + fmt(stats.fps, 1) + ' fps</div>' +
        (api.lastBench ? '<div>benchmark: ' + fmt(api.lastBench.ratio, 2) + '× real time (' + Math.round(api.lastBench.steps_per_second) + ' steps/s)</div>' : '') +
        (diverged ? '<div class="warn">diverged</div>' : '');
    }

    let last = performance.now();
    let debt = 0;
    let frameMs = 16;
    function tick(now) {
      window.requestAnimationFrame(tick);
      const dt = Math.min(0.1, Math.max(0, (now - last) / 1000));
      frameMs = 0.9 * frameMs + 0.1 * Math.min(200, now - last);
      last = now;
      if (playing && !diverged) {
        // Stepping may take 12 ms of a frame, more where frames are slow (software WebGL
        // drawing on the same cores), so that the simulation keeps up with real time at a
        // lower frame rate.
        const budget = Math.min(100, Math.max(12, 0.6 * frameMs));
        const t0 = performance.now();
        let frames = 0;
        if (speed === Infinity) {
          while (performance.now() - t0 < budget) {
            cloth.step(4);
            frames += 4;
          }
          debt = 0;
        } else {
          debt += dt * speed;
          while (debt >= cloth.frameDt && performance.now() - t0 < budget) {
            const chunk = Math.max(1, Math.min(8, Math.floor(debt / cloth.frameDt)));
            cloth.step(chunk);
            frames += chunk;
            debt -= chunk * cloth.frameDt;
          }
          // Behind real time: drop the backlog (the page runs slower than real time).
          if (debt > 4 * cloth.frameDt) debt = 0;
        }
        stats.stepMs += performance.now() - t0;
        stats.simSeconds += frames * cloth.frameDt;
        if (frames) checkFinite();
      }
      stats.renders++;
      if (view) view.render();
      updateStats(false);
    }

    // ---- controls ----
    $('play').addEventListener('click', () => setPlaying(!playing));
    $('reset').addEventListener('click', () => setScene(scene));
    $('stepone').addEventListener('click', () => {
      setPlaying(false);
      cloth.step(1);
      checkFinite();
      updateStats(true);
    });
    $('bench').addEventListener('click', () => {
      api.bench(2);
    });
    $('scene').addEventListener('change', (e) => setScene(e.target.value));
    $('speed').addEventListener('change', (e) => {
      speed = Number(e.target.value);
    });
    $('show').addEventListener('change', (e) => view && view.setShow(e.target.value));
    familySel.addEventListener('change', (e) => view && view.setFamily(e.target.value));
    window.addEventListener('keydown', (e) => {
      if (e.target && e.target.tagName === 'SELECT') return;
      if (e.key === ' ') {
        setPlaying(!playing);
        e.preventDefault();
      } else if (e.key === 'r') setScene(scene);
      else if (e.key === 's') $('stepone').click();
    });

    // ---- the scripting interface (web/README.md) ----
    const pause = () => setPlaying(false);
    Object.assign(api, {
      /** Rest state, zero velocity, exported pins held, no colliders (the "pinned" scene). */
      reset() {
        pause();
        setScene('pinned');
      },
      /** Advances `n` frames of frame_dt (with the substeps); true while the state is finite. */
      step(n) {
        pause();
        const ok = cloth.step(n == null ? 1 : n);
        if (!ok) checkFinite();
        updateStats(true);
        return ok;
      },
      /** Positions, flat [x0, y0, z0, x1, …] in particle order. */
      positions() {
        return Array.from(cloth.x);
      },
      /** Velocities, flat like positions(). */
      velocities() {
        return Array.from(cloth.v);
      },
      /** Sets positions and velocities (flat; v default zero) and, with `pinned`, the pinned particles. */
      setState(x, v, pinned) {
        pause();
        cloth.setState(x, v);
        if (pinned) cloth.setPinned(pinned);
        diverged = false;
        updateStats(true);
      },
      /** Pins the particles `list` where they are now (and frees the others). */
      setPinned(list) {
        pause();
        cloth.setPinned(list);
      },
      /** The pinned particles follow `frames` (flat [F, K, 3] for `particles`, default the pinned ones ascending); frame 0 is now. */
      setPinPath(frames, particles) {
        pause();
        cloth.setPinPath(frames, particles);
      },
      /** Drags particle `i` towards [x, y, z] (applied by step() and playback until release()). */
      drag(i, to) {
        pause();
        cloth.drag(i, to);
      },
      /** Ends the drag of `i` (of every particle without `i`). */
      release(i) {
        cloth.release(i);
      },
      /** `pinned` (default), `sphere` or `table`: the drop scenes release the sheet flat above a collider, no pins. */
      setScene(name) {
        pause();
        setScene(name);
      },
      play() {
        setPlaying(true);
      },
      pause,
      /** Simulated seconds per wall second of stepping, measured for about `seconds` s (the state is kept). */
      bench(seconds) {
        pause();
        const r = cloth.bench(seconds == null ? 2 : seconds);
        api.lastBench = r;
        updateStats(true);
        return r.ratio;
      },
      /** Particle `i` on the page in CSS pixels [x, y] (null without a 3-D view). */
      screenOf(i) {
        return view ? view.screenOf(i) : null;
      },
      /** What the page simulates. */
      info() {
        return {
          format: json.format,
          particles: c.particles,
          springs: c.springs,
          curvature: cloth.T,
          frame_dt: c.frameDt,
          substeps: c.substeps,
          dt: c.dt,
          mass: c.mass,
          mass_from: c.massSource,
          rayleigh: c.rayleigh,
          gravity: c.gravity,
          pinned: cloth.pinnedList(),
          stability: st,
          contact: cloth.contact,
          scene,
          time: cloth.time,
          frame: cloth.frame,
          webgl: api.webgl,
          playing,
        };
      },
    });
    Object.defineProperty(api, 'time', { get: () => cloth.time });

    if (view) {
      view.setFamily(familySel.value);
      view.frameCamera();
    }
    // Without pins the sheet would fall forever: open on the sphere instead (reset() still
    // gives the rest state).
    if (!cloth.pinnedList().length) setScene('sphere');
    setPlaying(playing);
    api.ready = true;
    updateStats(true);
    window.requestAnimationFrame(tick);
  }

  function load() {
    if (window.SPRINGTIME_SURROGATE) return start(window.SPRINGTIME_SURROGATE);
    // Without surrogate.js (a page served over http): fetch surrogate.json.
    if (window.location.protocol === 'file:') {
      return fatal(
        'surrogate.js is missing next to index.html: export a run with `springtime export RUN --format web --out DIR` and open DIR/index.html.',
        'surrogate.js is missing next to index.html: export a run with <code>springtime export RUN --format web --out DIR</code> and open DIR/index.html.',
      );
    }
    fetch('surrogate.json')
      .then((r) => {
        if (!r.ok) throw new Error('surrogate.json: HTTP ' + r.status);
        return r.json();
      })
      .then(start)
      .catch((e) => fatal('cannot load the surrogate: ' + String(e.message || e)));
  }

  load();
})();
