/* springtime web runtime: steps a learned mass-spring surrogate (`surrogate.json`) exactly as
 * `springtime simulate` does on the CPU, in single precision.
 *
 * A classic script (UMD): in a page it defines `window.SpringtimeSim`; in node,
 * `require('./sim.js')` or `import sim from './sim.js'` gives the same object.
 *
 * The step mirrors src/sim/mod.rs `step_frame` with the fused CPU kernel
 * (src/model/kernels/cpu.rs `chunk_forces`, `chunk_curvature`, `run_forces`, `step_lanes`):
 *
 *   per frame: pinned particles move from `here` to `next` at the velocity
 *              v̂ = (next − here)·(1/frame_dt); substep s of n targets here·(1−t) + next·t,
 *              t = (s+1)/n (the last one `next` itself);
 *   per substep, springs in file order, then curvature elements, then the mass scale:
 *     d = x_b − x_a, w = v_b − v_a, L² = d·d,  inv = 1/√L²,
 *     c = k (1 − l0·inv) + b (w·d) inv inv,   F_a += c d,  F_b −= c d        (Eq. 4, Eq. 2)
 *     with a viscosity β (`viscosity`, format /3): ν = β k, F_a += ν w, F_b −= ν w (per component,
 *     after c d)
 *     with shear springs softer in compression κ (`shear_compression`, format /4): a spring of
 *     `family` "shear" with 1 − l0·inv < 0 has k·κ in place of k in c (ν keeps k)
 *     e = x_i − 2 x_j + x_l:  F_i −= κ e, F_j += 2 κ e, F_l −= κ e          (curvature)
 *     F_i *= 1/w_i  (w_i = m_i / m: a mesh surrogate's relative masses; none on a grid)
 *     f = F + m g − c_R v,  v ← v + (h/m) f,  x ← x + h v                  (Eq. 5)
 *     pinned: x ← target, v ← v̂.
 *
 * Every operation is rounded to f32 (Math.fround; typed-array stores round too), in the
 * kernel's order, so the result matches the Rust kernel bit for bit where both compute the
 * same IEEE operations (Rust neither fuses multiply-adds nor reassociates).
 *
 * Contact (drop scenes) follows src/sim/contact.rs `Contact::apply_tensor` (the formula the
 * surrogate uses in `springtime drape`): a penalty pressure κφ + ζ·max(0, −n·v) per unit mass
 * inside the layer of thickness δ, and Coulomb friction regularised by the step.
 */
(function (root, factory) {
  if (typeof module === 'object' && module.exports) {
    module.exports = factory();
  } else {
    root.SpringtimeSim = factory();
  }
})(typeof globalThis !== 'undefined' ? globalThis : this, function () {
  'use strict';

  const fr = Math.fround;

  /** The format tags this runtime reads (src/export/mod.rs FORMAT, FORMAT_CURVATURE, FORMAT_VISCOSITY, FORMAT_COMPRESSION). */
  const FORMATS = ['springtime-surrogate/1', 'springtime-surrogate/2', 'springtime-surrogate/3', 'springtime-surrogate/4'];

  /** Semi-implicit Euler is stable while dt²ω² + 2·dt·γ stays below this (src/sim/stability.rs). */
  const STABILITY_LIMIT = 4.0;

  /** The paper's sheet side, m: drop scenes are the drape scenes (configs/scenes) scaled to the sheet. */
  const PAPER_SIZE = 15.5;

  function fail(msg) {
    throw new Error('surrogate.json: ' + msg);
  }

  function isArr(a) {
    return Array.isArray(a) || ArrayBuffer.isView(a);
  }

  /**
   * Checks a parsed surrogate.json and fills in what older exports lack. Returns the physics
   * constants the runtime uses: `{frameDt, substeps, mass, massSource, ...}`.
   */
  function constants(json) {
    if (!json || typeof json !== 'object') fail('not an object');
    if (!FORMATS.includes(json.format)) {
      fail('key `format` is ' + JSON.stringify(json.format) + ', expected one of ' + FORMATS.join(', '));
    }
    const p = json.rest_positions && json.rest_positions.length;
    if (!p) fail('key `rest_positions` is empty');
    if (!isArr(json.masses) || json.masses.length !== p) fail('key `masses` needs one entry per particle');
    const s = json.springs ? json.springs.length : 0;
    for (const key of ['rest_length', 'k', 'b']) {
      if (!isArr(json[key]) || json[key].length !== s) fail('key `' + key + '` needs one entry per spring');
    }
    for (const [a, b] of json.springs) {
      if (!(a >= 0 && a < p && b >= 0 && b < p && a !== b)) fail('spring (' + a + ', ' + b + ') is not a pair of particles');
    }
    const viscosity = json.viscosity || 0;
    if (!(isFinite(viscosity) && viscosity >= 0)) fail('key `viscosity` must be finite and non-negative');
    const shearCompression = json.shear_compression == null ? 1 : json.shear_compression;
    if (!(shearCompression >= 0 && shearCompression <= 1)) fail('key `shear_compression` must be from 0 to 1');
    const compressed = shearCompression !== 1;
    if (compressed !== (json.format === 'springtime-surrogate/4')) {
      fail('key `shear_compression` is ' + shearCompression + ' with `format` ' + JSON.stringify(json.format) + ': shear springs softer in compression need springtime-surrogate/4 and /4 them');
    }
    if (compressed && !(isArr(json.family) && json.family.length === s)) fail('key `family` needs one entry per spring');
    if (!compressed && (viscosity !== 0) !== (json.format === 'springtime-surrogate/3')) {
      fail('key `viscosity` is ' + viscosity + ' with `format` ' + JSON.stringify(json.format) + ': a viscosity needs springtime-surrogate/3 (or /4) and /3 one');
    }
    const curv = json.curvature || [];
    const curvK = json.curvature_k || [];
    if (curv.length !== curvK.length) fail('keys `curvature` and `curvature_k` differ in length');
    for (const t of curv) {
      if (!t.every((i) => i >= 0 && i < p)) fail('curvature element ' + JSON.stringify(t) + ' past the particles');
    }
    // Frame time and substeps: `frame_dt` and `substeps` when exported; else the integration
    // step `dt` as one substep per frame.
    let frameDt = json.frame_dt;
    let substeps = json.substeps;
    if (frameDt == null && substeps != null && json.dt != null) frameDt = json.dt * substeps;
    if (substeps == null && frameDt != null && json.dt != null) substeps = Math.max(1, Math.round(frameDt / json.dt));
    if (frameDt == null && json.dt != null) {
      frameDt = json.dt;
      substeps = 1;
    }
    if (frameDt == null) fail('no `frame_dt` (nor `dt`): cannot step');
    if (substeps == null) substeps = 1;
    if (!(frameDt > 0 && isFinite(frameDt))) fail('`frame_dt` must be positive');
    if (!(Number.isInteger(substeps) && substeps >= 1)) fail('`substeps` must be a positive integer');
    // The mean particle mass m of the integrator (`Physics.mass`): the key `mass` when
    // exported; on a grid every particle weighs it; else the mean of the masses.
    let mass = json.mass;
    let massSource = 'mass';
    if (mass == null) {
      const first = json.masses[0];
      if (json.masses.every((m) => m === first)) {
        mass = first;
        massSource = 'masses (all equal)';
      } else {
        mass = json.masses.reduce((a, b) => a + b, 0) / p;
        massSource = 'mean of masses';
      }
    }
    if (!(mass > 0 && isFinite(mass))) fail('the particle mass must be positive');
    return {
      particles: p,
      springs: s,
      frameDt,
      substeps,
      dt: frameDt / substeps,
      mass,
      massSource,
      rayleigh: json.rayleigh || 0,
      gravity: json.gravity || [0, 0, -9.81],
      viscosity,
      shearCompression,
    };
  }

  /**
   * Largest eigenvalue of Σ_s w_s u_s u_sᵀ over the rest directions u_s, by the power iteration
   * of src/cloth/topology.rs `max_eigenvalue` (with relative masses `weight`, of W^-½ … W^-½).
   */
  function maxEigenvalue(rest, springs, restLength, weights, massWeight) {
    const p = rest.length;
    const dirs = springs.map(([a, b], s) => {
      const l = restLength[s];
      return [(rest[b][0] - rest[a][0]) / l, (rest[b][1] - rest[a][1]) / l, 0];
    });
    let y = [];
    for (let i = 0; i < p; i++) y.push([Math.sin(i * 0.7548) + 0.3, Math.cos(i * 1.3247) - 0.2, Math.sin(i * 0.5698)]);
    const scale = massWeight ? massWeight.map((w) => 1 / Math.sqrt(w)) : new Array(p).fill(1);
    let lambda = 0;
    for (let it = 0; it < 300; it++) {
      const z = [];
      for (let i = 0; i < p; i++) z.push([0, 0, 0]);
      springs.forEach(([a, b], s) => {
        const u = dirs[s];
        const ya = y[a].map((c) => c * scale[a]);
        const yb = y[b].map((c) => c * scale[b]);
        const proj = weights[s] * (u[0] * (yb[0] - ya[0]) + u[1] * (yb[1] - ya[1]) + u[2] * (yb[2] - ya[2]));
        for (let i = 0; i < 3; i++) {
          z[b][i] += proj * u[i] * scale[b];
          z[a][i] -= proj * u[i] * scale[a];
        }
      });
      let nz = 0;
      let ny = 0;
      for (let i = 0; i < p; i++) {
        for (let c = 0; c < 3; c++) {
          nz += z[i][c] * z[i][c];
          ny += y[i][c] * y[i][c];
        }
      }
      nz = Math.sqrt(nz);
      ny = Math.sqrt(ny);
      if (nz === 0 || ny === 0) return 0;
      lambda = nz / ny;
      y = z.map((v) => [v[0] / nz, v[1] / nz, v[2] / nz]);
    }
    return lambda;
  }

  /**
   * The stability number dt²ω² + 2·dt·γ of the surrogate at its step (src/sim/stability.rs
   * `Stability::estimate(..).with_curvature(..)`): the key `stability.number` when exported,
   * else computed here the same way.
   */
  function stability(json, c) {
    if (json.stability && typeof json.stability.number === 'number') {
      return {
        number: json.stability.number,
        limit: json.stability.limit || STABILITY_LIMIT,
        source: 'surrogate.json',
      };
    }
    const pos = (v) => Array.from(v, (x) => Math.max(x, 0));
    const weights = json.masses.every((m) => m === json.masses[0]) && json.grid ? null : json.masses.map((m) => m / c.mass);
    let omega2 = maxEigenvalue(json.rest_positions, json.springs, json.rest_length, pos(json.k), weights) / c.mass;
    // A viscosity counts as damping β k along each spring (src/sim/mod.rs `stability_of`).
    const damping = json.b.map((b, s) => b + c.viscosity * json.k[s]);
    const gamma = (maxEigenvalue(json.rest_positions, json.springs, json.rest_length, pos(damping), weights) + Math.max(c.rayleigh, 0)) / c.mass;
    const curv = json.curvature || [];
    if (curv.length) {
      const row = new Float64Array(c.particles);
      curv.forEach(([i, j, l], t) => {
        const k = 4 * Math.max(json.curvature_k[t], 0);
        row[i] += k;
        row[j] += 2 * k;
        row[l] += k;
      });
      omega2 += row.reduce((a, b) => Math.max(a, b), 0) / c.mass;
    }
    const dt = c.dt;
    return { number: dt * dt * omega2 + 2 * dt * gamma, limit: STABILITY_LIMIT, omega2, gamma, source: 'computed' };
  }

  /** Contact constants for a sheet of larger side `size` at step `h` (src/sim/contact.rs `ContactConfig::resolve`, all "auto"). */
  function contactParams(size, h, number) {
    const s = Math.min(1, Math.max(0.02, (3.9 - number) / 0.75));
    return { thickness: 0.01 * size, stiffness: (0.25 * s) / (h * h), damping: (0.25 * s) / h };
  }

  // ---- colliders: signed distance, outward normal and closest point (src/sim/contact.rs `hit`) ----

  /** A ball of `radius` about `center`. */
  function sphere(center, radius, friction) {
    return {
      kind: 'sphere',
      center,
      radius,
      friction: friction == null ? 0.5 : friction,
      hit(x, y, z, out) {
        const dx = x - center[0];
        const dy = y - center[1];
        const dz = z - center[2];
        const len = Math.sqrt(dx * dx + dy * dy + dz * dz);
        let nx = 0;
        let ny = 0;
        let nz = 1;
        if (len > 1e-12) {
          nx = dx / len;
          ny = dy / len;
          nz = dz / len;
        }
        out.distance = len - radius;
        out.nx = nx;
        out.ny = ny;
        out.nz = nz;
        out.px = center[0] + nx * radius;
        out.py = center[1] + ny * radius;
        out.pz = center[2] + nz * radius;
      },
    };
  }

  /** The axis of the face of the box of half sizes `half` nearest to `q` (inside or on it). */
  function nearestFace(half, q) {
    let axis = 2;
    let best = Infinity;
    for (let c = 0; c < 3; c++) {
      const gap = half[c] - Math.abs(q[c]);
      if (gap < best) {
        best = gap;
        axis = c;
      }
    }
    return axis;
  }

  /** An axis-aligned box of inner half sizes `half` rounded by `radius` (the drape table). */
  function roundedBox(center, half, radius, friction) {
    return {
      kind: 'rounded_box',
      center,
      half,
      radius,
      friction: friction == null ? 0.5 : friction,
      hit(x, y, z, out) {
        const q = [x - center[0], y - center[1], z - center[2]];
        const p = [0, 0, 0];
        let inside = true;
        for (let c = 0; c < 3; c++) {
          p[c] = Math.min(half[c], Math.max(-half[c], q[c]));
          if (p[c] !== q[c]) inside = false;
        }
        let axis = 2;
        if (inside) {
          // Inside the inner box: the nearest face.
          axis = nearestFace(half, q);
          p[axis] = q[axis] >= 0 ? half[axis] : -half[axis];
        }
        const d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
        const len = Math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        let n;
        if (len > 1e-12) {
          n = inside ? [-d[0] / len, -d[1] / len, -d[2] / len] : [d[0] / len, d[1] / len, d[2] / len];
        } else {
          n = [0, 0, 0];
          if (!inside) {
            // On the inner box's surface: the face's normal.
            axis = nearestFace(half, q);
          }
          n[axis] = q[axis] >= 0 ? 1 : -1;
        }
        out.distance = (inside ? -len : len) - radius;
        out.nx = n[0];
        out.ny = n[1];
        out.nz = n[2];
        out.px = center[0] + p[0] + n[0] * radius;
        out.py = center[1] + p[1] + n[1] * radius;
        out.pz = center[2] + p[2] + n[2] * radius;
      },
    };
  }

  /** The half-space z < `height` (the floor). */
  function ground(height, friction) {
    return {
      kind: 'plane',
      height,
      friction: friction == null ? 0.5 : friction,
      hit(x, y, z, out) {
        out.distance = z - height;
        out.nx = 0;
        out.ny = 0;
        out.nz = 1;
        out.px = x;
        out.py = y;
        out.pz = height;
      },
    };
  }

  /**
   * The drop scenes of `springtime drape` (configs/scenes/sphere.toml, table.toml) scaled from
   * the paper's 15.5 m sheet to one of larger side `size`: colliders below the origin, the sheet
   * released flat `release` above their top, plus a floor.
   */
  function dropScene(name, size) {
    const u = size / PAPER_SIZE;
    if (name === 'sphere') {
      const r = 3 * u;
      return { colliders: [sphere([0, 0, -r], r, 0.5), ground(-2 * r, 0.5)], release: 1 * u };
    }
    if (name === 'table') {
      const half = [3 * u, 3 * u, 1.5 * u];
      const r = 0.25 * u;
      const top = 0;
      const cz = top - half[2] - r;
      return { colliders: [roundedBox([0, 0, cz], half, r, 0.5), ground(cz - half[2] - r, 0.5)], release: 1 * u };
    }
    throw new Error('unknown scene ' + JSON.stringify(name) + ' (sphere, table)');
  }

  /** A surrogate being stepped: state, pins, drags and colliders. */
  class Cloth {
    /** `json`: a parsed surrogate.json (the object `window.SPRINGTIME_SURROGATE` holds). */
    constructor(json) {
      const c = constants(json);
      this.json = json;
      this.constants = c;
      const p = c.particles;
      const s = c.springs;
      this.n = p;
      this.S = s;
      this.frameDt = c.frameDt;
      this.substeps = c.substeps;
      this.mass = c.mass;
      // The kernel's constants, cast to f32 from f64 as src/model/kernels/cpu.rs `step_lanes`.
      const h = c.frameDt / c.substeps;
      this.h64 = h;
      this.h = fr(h);
      this.hm = fr(h / c.mass);
      this.cR = fr(c.rayleigh);
      // The viscosity per unit stiffness, cast to f32 as src/model/kernels/cpu.rs `with_viscosity`.
      this.visc = fr(c.viscosity);
      // Each spring's stiffness in compression per unit k, f32 as cpu.rs `with_compression`.
      this.comp = new Float32Array(s).fill(1);
      if (c.shearCompression !== 1) {
        json.family.forEach((f, i) => {
          if (f === 'shear') this.comp[i] = c.shearCompression;
        });
      }
      this.mg = new Float32Array(c.gravity.map((g) => g * c.mass));
      this.invFrameDt = fr(1 / c.frameDt);
      this.ia = new Int32Array(s);
      this.ib = new Int32Array(s);
      json.springs.forEach(([a, b], i) => {
        this.ia[i] = a;
        this.ib[i] = b;
      });
      this.k = Float32Array.from(json.k);
      this.b = Float32Array.from(json.b);
      this.l0 = Float32Array.from(json.rest_length);
      const curv = json.curvature || [];
      this.T = curv.length;
      this.ci = Int32Array.from(curv, (t) => t[0]);
      this.cj = Int32Array.from(curv, (t) => t[1]);
      this.cl = Int32Array.from(curv, (t) => t[2]);
      this.ck = Float32Array.from(json.curvature_k || []);
      // 1/w per particle (w = m_i / m), as src/cloth/topology.rs `force_scale`; none when all
      // particles weigh m (a grid).
      const w = json.masses.map((m) => m / c.mass);
      this.scale = w.every((x) => x === 1) ? null : Float32Array.from(w, (x) => 1 / x);
      this.rest = new Float32Array(3 * p);
      json.rest_positions.forEach((q, i) => {
        this.rest[3 * i] = q[0];
        this.rest[3 * i + 1] = q[1];
        this.rest[3 * i + 2] = q[2];
      });
      this.x = new Float32Array(3 * p);
      this.v = new Float32Array(3 * p);
      this.f = new Float32Array(3 * p);
      // Pins: flags (pinned or dragged this frame), where they are at the frame's start and
      // where they go at its end, their velocity and the substep's target.
      this.pinned = new Uint8Array(p);
      this.active = new Uint8Array(p);
      this.here = new Float32Array(3 * p);
      this.next = new Float32Array(3 * p);
      this.pinV = new Float32Array(3 * p);
      this.target = new Float32Array(3 * p);
      this.path = null;
      this.drags = new Map();
      // Fastest a dragged particle follows its target, m/s (a jump would tear the sheet).
      this.dragSpeed = 10 * Math.max(json.width || 1, json.height || 1);
      this.colliders = [];
      this.contact = null;
      this.frame = 0;
      this.stability = null;
      this._hit = { distance: 0, nx: 0, ny: 0, nz: 0, px: 0, py: 0, pz: 0 };
      this.reset();
    }

    /** Simulated time since the last reset or state, s. */
    get time() {
      return this.frame * this.frameDt;
    }

    /** The stability number of the step (computed once, on first use). */
    getStability() {
      if (!this.stability) this.stability = stability(this.json, this.constants);
      return this.stability;
    }

    /** The rest state, zero velocity, the exported pins held there, no colliders or drags. */
    reset() {
      this.x.set(this.rest);
      this.v.fill(0);
      this.setPinned(this.json.pinned || []);
      this.here.set(this.x);
      this.path = null;
      this.drags.clear();
      this.colliders = [];
      this.contact = null;
      this.frame = 0;
    }

    /** Pinned particle indices, ascending. */
    pinnedList() {
      const out = [];
      for (let i = 0; i < this.n; i++) if (this.pinned[i]) out.push(i);
      return out;
    }

    /** Pins the particles `list` (and frees the others), held where they are now. */
    setPinned(list) {
      this.pinned.fill(0);
      for (const i of list) {
        if (!(Number.isInteger(i) && i >= 0 && i < this.n)) throw new Error('no particle ' + i);
        this.pinned[i] = 1;
      }
      this.here.set(this.x);
      this.path = null;
    }

    /** Sets positions `x` and velocities `v` (flat `[x0, y0, z0, x1, …]`; `v` default zero); pins are held at `x`. */
    setState(x, v) {
      if (!x || x.length !== 3 * this.n) throw new Error('setState: x needs ' + 3 * this.n + ' values');
      if (v && v.length !== 3 * this.n) throw new Error('setState: v needs ' + 3 * this.n + ' values');
      this.x.set(x);
      if (v) this.v.set(v);
      else this.v.fill(0);
      this.here.set(this.x);
      this.path = null;
      this.drags.clear();
      this.frame = 0;
    }

    /**
     * The pinned particles follow a recorded path: `frames` is flat `[F, K, 3]` for the K
     * particles `particles` (default: the pinned ones, ascending); frame 0 is now, frame j is
     * reached after j frames, and after the last frame they hold there (as `springtime
     * simulate`, which clamps to the rollout's last frame).
     */
    setPinPath(frames, particles) {
      const ids = particles || this.pinnedList();
      const k = ids.length;
      if (!k) throw new Error('setPinPath: no pinned particles');
      if (!frames || frames.length % (3 * k) !== 0 || frames.length === 0) {
        throw new Error('setPinPath: frames must hold F × ' + k + ' × 3 values');
      }
      for (const i of ids) {
        if (!this.pinned[i]) throw new Error('setPinPath: particle ' + i + ' is not pinned');
      }
      this.path = { ids: Int32Array.from(ids), frames: Float32Array.from(frames), count: frames.length / (3 * k), start: this.frame };
      // Frame 0 of the path is where the pins are now.
      this._pathFrame(0, this.here);
    }

    _pathFrame(j, dst) {
      const p = this.path;
      const jj = Math.min(j, p.count - 1);
      const k = p.ids.length;
      const base = jj * k * 3;
      for (let q = 0; q < k; q++) {
        const i = p.ids[q];
        dst[3 * i] = p.frames[base + 3 * q];
        dst[3 * i + 1] = p.frames[base + 3 * q + 1];
        dst[3 * i + 2] = p.frames[base + 3 * q + 2];
      }
    }

    /**
     * Drags particle `i` towards `to` ([x, y, z]): while dragged it moves like a pin, at most
     * `dragSpeed` m/s. A dragged pinned particle stays where it is released; a free one is
     * let go with its drag velocity. Dragging a pinned particle ends a pin path.
     */
    drag(i, to) {
      if (!(Number.isInteger(i) && i >= 0 && i < this.n)) throw new Error('drag: no particle ' + i);
      if (!to || to.length !== 3 || !to.every(Number.isFinite)) throw new Error('drag: target must be [x, y, z]');
      if (this.pinned[i] && this.path) this.path = null;
      this.drags.set(i, [to[0], to[1], to[2]]);
    }

    /** Ends the drag of particle `i` (all drags without `i`). */
    release(i) {
      const ids = i == null ? Array.from(this.drags.keys()) : [i];
      for (const j of ids) {
        if (!this.drags.has(j)) continue;
        this.drags.delete(j);
        if (this.pinned[j]) {
          for (let c = 0; c < 3; c++) this.here[3 * j + c] = this.x[3 * j + c];
        }
      }
    }

    /** Colliders (see `sphere`, `roundedBox`, `ground`, `dropScene`) with contact constants `params` (default: `contactParams` for the sheet). */
    setColliders(colliders, params) {
      this.colliders = colliders || [];
      if (!this.colliders.length) {
        this.contact = null;
        return;
      }
      const size = Math.max(this.json.width || 1, this.json.height || 1);
      this.contact = params || contactParams(size, this.h64, this.getStability().number);
    }

    /** Advances `n` frames (default 1). Returns false if the state is no longer finite. */
    step(n) {
      const frames = n == null ? 1 : n;
      for (let j = 0; j < frames; j++) this.stepFrame();
      return this.finite();
    }

    /** Whether every position and velocity is finite. */
    finite() {
      for (let i = 0; i < this.x.length; i++) {
        if (!Number.isFinite(this.x[i]) || !Number.isFinite(this.v[i])) return false;
      }
      return true;
    }

    /** One frame: `substeps` semi-implicit Euler steps, pins moving from `here` to `next`. */
    stepFrame() {
      const n3 = 3 * this.n;
      const { here, next, pinV, active, pinned } = this;
      active.set(pinned);
      next.set(here);
      if (this.path) this._pathFrame(this.frame - this.path.start + 1, next);
      for (const [i, to] of this.drags) {
        // A dragged particle starts the frame where it is.
        active[i] = 1;
        const maxStep = this.dragSpeed * this.frameDt;
        let dx = to[0] - this.x[3 * i];
        let dy = to[1] - this.x[3 * i + 1];
        let dz = to[2] - this.x[3 * i + 2];
        const len = Math.sqrt(dx * dx + dy * dy + dz * dz);
        if (len > maxStep) {
          dx *= maxStep / len;
          dy *= maxStep / len;
          dz *= maxStep / len;
        }
        here[3 * i] = this.x[3 * i];
        here[3 * i + 1] = this.x[3 * i + 1];
        here[3 * i + 2] = this.x[3 * i + 2];
        next[3 * i] = this.x[3 * i] + dx;
        next[3 * i + 1] = this.x[3 * i + 1] + dy;
        next[3 * i + 2] = this.x[3 * i + 2] + dz;
      }
      // v̂ = (next − here) · (1/frame_dt), in f32 (tensor ops of `step_frame`).
      const inv = this.invFrameDt;
      for (let q = 0; q < n3; q++) pinV[q] = active[(q / 3) | 0] ? fr(fr(next[q] - here[q]) * inv) : 0;
      const ns = this.substeps;
      for (let sub = 0; sub < ns; sub++) {
        let target = next;
        if (sub + 1 !== ns) {
          target = this.target;
          const t = (sub + 1) / ns;
          const a = fr(1 - t);
          const b = fr(t);
          for (let q = 0; q < n3; q++) target[q] = fr(fr(here[q] * a) + fr(next[q] * b));
        }
        this.forces(this.x, this.v, this.f);
        if (this.contact) {
          // As `step_frame` with contact: the net force, then the contact forces on it.
          this.addExternal(this.f);
          this.applyContact(this.f);
          this.integrate(target, true);
        } else {
          this.integrate(target, false);
        }
      }
      here.set(next);
      this.frame++;
    }

    /** Internal forces at (x, v) into `out`: springs, curvature, mass scale (the fused kernel's order). */
    forces(x, v, out) {
      out.fill(0);
      const { ia, ib, k, b, l0, visc, comp } = this;
      const S = this.S;
      for (let s = 0; s < S; s++) {
        const a = 3 * ia[s];
        const e = 3 * ib[s];
        const d0 = fr(x[e] - x[a]);
        const d1 = fr(x[e + 1] - x[a + 1]);
        const d2 = fr(x[e + 2] - x[a + 2]);
        const w0 = fr(v[e] - v[a]);
        const w1 = fr(v[e + 1] - v[a + 1]);
        const w2 = fr(v[e + 2] - v[a + 2]);
        const len2 = fr(fr(fr(d0 * d0) + fr(d1 * d1)) + fr(d2 * d2));
        const wd = fr(fr(fr(w0 * d0) + fr(w1 * d1)) + fr(w2 * d2));
        const iv = fr(1 / fr(Math.sqrt(len2)));
        const st = fr(1 - fr(l0[s] * iv));
        const kl = st < 0 ? fr(k[s] * comp[s]) : k[s];
        const coef = fr(fr(kl * st) + fr(fr(fr(b[s] * wd) * iv) * iv));
        let c0 = fr(coef * d0);
        let c1 = fr(coef * d1);
        let c2 = fr(coef * d2);
        const nu = fr(visc * k[s]);
        if (nu !== 0) {
          c0 = fr(c0 + fr(nu * w0));
          c1 = fr(c1 + fr(nu * w1));
          c2 = fr(c2 + fr(nu * w2));
        }
        out[a] += c0;
        out[e] -= c0;
        out[a + 1] += c1;
        out[e + 1] -= c1;
        out[a + 2] += c2;
        out[e + 2] -= c2;
      }
      const T = this.T;
      if (T) {
        const { ci, cj, cl, ck } = this;
        for (let t = 0; t < T; t++) {
          const kt = ck[t];
          const i = 3 * ci[t];
          const j = 3 * cj[t];
          const l = 3 * cl[t];
          for (let c = 0; c < 3; c++) {
            const e = fr(fr(x[i + c] - fr(2 * x[j + c])) + x[l + c]);
            const f = fr(kt * e);
            out[i + c] += -f;
            out[j + c] += fr(2 * f);
            out[l + c] += -f;
          }
        }
      }
      const sc = this.scale;
      if (sc) {
        const n3 = 3 * this.n;
        for (let q = 0; q < n3; q++) out[q] *= sc[(q / 3) | 0];
      }
    }

    /** Adds gravity and Rayleigh damping to the internal forces `f`: f = F + m g − c v. */
    addExternal(f) {
      const { v, mg } = this;
      const c = this.cR;
      const n3 = 3 * this.n;
      for (let q = 0; q < n3; q++) f[q] = fr(fr(f[q] + mg[q % 3]) - fr(c * v[q]));
    }

    /**
     * f = F + m g − c v (unless `net`: `f` holds it already), v ← v + (h/m) f, x ← x + h v;
     * pinned and dragged particles take `target` and v̂.
     */
    integrate(target, net) {
      const { x, v, f, mg, active, pinV } = this;
      const h = this.h;
      const hm = this.hm;
      const c = this.cR;
      const n = this.n;
      for (let i = 0; i < n; i++) {
        const q = 3 * i;
        if (active[i]) {
          x[q] = target[q];
          x[q + 1] = target[q + 1];
          x[q + 2] = target[q + 2];
          v[q] = pinV[q];
          v[q + 1] = pinV[q + 1];
          v[q + 2] = pinV[q + 2];
          continue;
        }
        for (let k = 0; k < 3; k++) {
          const fi = net ? f[q + k] : fr(fr(f[q + k] + mg[k]) - fr(c * v[q + k]));
          const vn = fr(v[q + k] + fr(hm * fi));
          v[q + k] = vn;
          x[q + k] = fr(x[q + k] + fr(h * vn));
        }
      }
    }

    /**
     * Adds the contact forces at the substep's start to the net forces `f` as
     * src/sim/contact.rs `Contact::apply_tensor` does, in f32 and in its order: per collider,
     * the normal n and the closest point's offset n·p found in f64 at x (static colliders,
     * surface velocity 0), then
     *   φ = max(0, δ − (n·x − n·p)),  f_n = (κ φ + ζ max(0, −n·v)) m,
     *   w = v + (f + n f_n)(h/m),  w_t = w − n (n·w),  r = min(μ f_n / √(w_t·w_t + 10⁻²⁴), m/h),
     *   f ← f + n f_n − w_t r.
     * Pinned and dragged particles take none.
     */
    applyContact(f) {
      const { x, v, active } = this;
      const prm = this.contact;
      const hit = this._hit;
      const delta = fr(prm.thickness);
      const kappa = fr(prm.stiffness);
      const zeta = fr(prm.damping);
      const mass = fr(this.mass);
      const hm = fr(this.h64 / this.mass);
      const cap = fr(this.mass / this.h64);
      const eps = fr(1e-24);
      for (const col of this.colliders) {
        const mu = fr(col.friction);
        for (let i = 0; i < this.n; i++) {
          if (active[i]) continue;
          const q = 3 * i;
          col.hit(x[q], x[q + 1], x[q + 2], hit);
          if (!(hit.distance < prm.thickness)) continue;
          const nx = fr(hit.nx);
          const ny = fr(hit.ny);
          const nz = fr(hit.nz);
          const offset = fr(hit.nx * hit.px + hit.ny * hit.py + hit.nz * hit.pz);
          const dist = fr(fr(fr(fr(nx * x[q]) + fr(ny * x[q + 1])) + fr(nz * x[q + 2])) - offset);
          const phi = Math.max(fr(-dist + delta), 0);
          const vn = fr(fr(fr(nx * v[q]) + fr(ny * v[q + 1])) + fr(nz * v[q + 2]));
          const approach = Math.max(-vn, 0);
          const fn = fr(fr(fr(phi * kappa) + fr(approach * zeta)) * mass);
          const wx = fr(v[q] + fr(fr(f[q] + fr(nx * fn)) * hm));
          const wy = fr(v[q + 1] + fr(fr(f[q + 1] + fr(ny * fn)) * hm));
          const wz = fr(v[q + 2] + fr(fr(f[q + 2] + fr(nz * fn)) * hm));
          const wn = fr(fr(fr(nx * wx) + fr(ny * wy)) + fr(nz * wz));
          const tx = fr(wx - fr(nx * wn));
          const ty = fr(wy - fr(ny * wn));
          const tz = fr(wz - fr(nz * wn));
          const norm = fr(Math.sqrt(fr(fr(fr(fr(tx * tx) + fr(ty * ty)) + fr(tz * tz)) + eps)));
          const r = Math.min(fr(fr(fn * mu) / norm), cap);
          f[q] = fr(fr(f[q] + fr(nx * fn)) - fr(tx * r));
          f[q + 1] = fr(fr(f[q + 1] + fr(ny * fn)) - fr(ty * r));
          f[q + 2] = fr(fr(f[q + 2] + fr(nz * fn)) - fr(tz * r));
        }
      }
    }

    /**
     * Releases the sheet flat above the drop scene `name` (`sphere`, `table`) without pins, as
     * `springtime drape` does; `none` goes back to the rest state with the exported pins.
     */
    dropOn(name) {
      if (name === 'none' || name == null) {
        this.reset();
        return null;
      }
      const size = Math.max(this.json.width || 1, this.json.height || 1);
      const scene = dropScene(name, size);
      const w = this.json.width || 0;
      const hh = this.json.height || 0;
      const x = new Float32Array(3 * this.n);
      // As `Scene::release`: the rest rectangle centred on the origin, in f64, then f32.
      this.json.rest_positions.forEach((q, i) => {
        x[3 * i] = q[0] - w / 2;
        x[3 * i + 1] = q[1] - hh / 2;
        x[3 * i + 2] = scene.release;
      });
      this.setState(x);
      this.setPinned([]);
      this.setColliders(scene.colliders);
      return scene;
    }

    /** A copy of everything `stepFrame` changes (for `bench`). */
    snapshot() {
      return {
        x: this.x.slice(),
        v: this.v.slice(),
        here: this.here.slice(),
        frame: this.frame,
        path: this.path,
        drags: new Map(this.drags),
      };
    }

    restore(s) {
      this.x.set(s.x);
      this.v.set(s.v);
      this.here.set(s.here);
      this.frame = s.frame;
      this.path = s.path;
      this.drags = new Map(s.drags);
    }

    /**
     * Simulated seconds per wall second: steps from the current state for about `seconds`
     * wall seconds (`now` a clock in ms), then puts the state back.
     */
    bench(seconds, now) {
      const clock = now || (() => (typeof performance !== 'undefined' ? performance.now() : Date.now()));
      const snap = this.snapshot();
      const budget = 1000 * (seconds == null ? 1 : seconds);
      let frames = 0;
      const t0 = clock();
      let t = t0;
      let chunk = 1;
      while (t - t0 < budget) {
        this.step(chunk);
        frames += chunk;
        t = clock();
        if (t - t0 < budget / 20) chunk *= 2;
      }
      this.restore(snap);
      const wall = (t - t0) / 1000;
      return { ratio: (frames * this.frameDt) / wall, frames, wall, steps_per_second: (frames * this.substeps) / wall };
    }
  }

  return {
    Cloth,
    FORMATS,
    STABILITY_LIMIT,
    constants,
    stability,
    contactParams,
    maxEigenvalue,
    sphere,
    roundedBox,
    ground,
    dropScene,
  };
});
