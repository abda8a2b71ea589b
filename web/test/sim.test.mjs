// Unit tests of the web runtime's step (web/src/sim.js) on cases small enough to compute by
// hand: `node --test web/test/`.
import assert from 'node:assert/strict';
import test from 'node:test';

import sim from '../src/sim.js';

const { Cloth } = sim;
const fr = Math.fround;

/** Two particles `a` = (0,0,0) and `b` = (len,0,0), one spring of rest length 1. */
function pair({ k = 10, b = 0, len = 1.5, rayleigh = 0, gravity = [0, 0, 0], mass = 0.5, frameDt = 0.01, substeps = 1, pinned = [] } = {}) {
  return {
    format: 'springtime-surrogate/1',
    units: 'SI',
    grid: null,
    triangles: [],
    width: 1,
    height: 1,
    masses: [mass, mass],
    rest_positions: [[0, 0, 0], [len, 0, 0]],
    springs: [[0, 1]],
    family: ['structural'],
    rest_length: [1],
    k: [k],
    b: [b],
    pinned,
    rayleigh,
    gravity,
    dt: frameDt / substeps,
    frame_dt: frameDt,
    substeps,
    mass,
  };
}

const close = (a, b, tol, what) => assert.ok(Math.abs(a - b) <= tol, `${what}: ${a} vs ${b} (tolerance ${tol})`);

test('a stretched spring pulls both ends together by Hooke (one substep by hand)', () => {
  // |d| = 1.5, l0 = 1: f_a = k (1 − l0/|d|) d = 10 · (1/3) · 1.5 = 5 N along +x, f_b = −5 N.
  // v' = h/m f = 0.01/0.5 · 5 = 0.1 m/s; x' = x + h v' = ±0.001 m.
  const c = new Cloth(pair());
  c.step(1);
  close(c.v[0], 0.1, 1e-7, 'v_a');
  close(c.v[3], -0.1, 1e-7, 'v_b');
  close(c.x[0], 0.001, 1e-9, 'x_a');
  close(c.x[3], 1.5 - 0.001, 1e-7, 'x_b');
  for (const q of [1, 2, 4, 5]) assert.equal(c.x[q], 0);
  // Momentum: equal masses move symmetrically.
  assert.equal(c.v[0], -c.v[3]);
});

test('the spring force is exactly Eq. 4 in f32', () => {
  const c = new Cloth(pair({ k: 7.3, b: 0.9, len: 1.3 }));
  c.v.set([0.2, -0.1, 0.05, -0.3, 0.4, 0.0]);
  c.forces(c.x, c.v, c.f);
  const d = [fr(1.3), 0, 0];
  const w = [fr(-0.5), fr(0.5), fr(-0.05)];
  const len = Math.hypot(...d);
  const expect = (7.3 * (1 - 1 / len) + (0.9 * (w[0] * d[0])) / (len * len)) * d[0];
  close(c.f[0], expect, 1e-5, 'F_a');
  close(c.f[3], -expect, 1e-5, 'F_b');
  assert.equal(c.f[1], 0, 'damping acts along the spring only');
});

test('damping along the spring resists the ends separating (one substep by hand)', () => {
  // At rest length, ends separating at 1 m/s: f_a = b (w·d) d/|d|² = 2 · 1 · 1 / 1 = 2 N (+x).
  const c = new Cloth(pair({ k: 10, b: 2, len: 1 }));
  c.v.set([-0.5, 0, 0, 0.5, 0, 0]);
  c.step(1);
  // v_a' = −0.5 + h/m · 2 = −0.5 + 0.04.
  close(c.v[0], -0.46, 1e-7, 'v_a');
  close(c.v[3], 0.46, 1e-7, 'v_b');
  close(c.x[0], -0.0046, 1e-9, 'x_a');
});

test('a viscosity damps the whole relative velocity of the ends, across the spring too (one substep by hand)', () => {
  // At rest length, b = 0, end a moving at 1 m/s across the spring (+y), β = 0.01 s:
  // ν = β k = 0.1 N·s/m, w = v_b − v_a = (0, −1, 0), F_a = ν w = −0.1 N (y), F_b = +0.1 N.
  const json = { ...pair({ k: 10, b: 0, len: 1 }), format: 'springtime-surrogate/3', viscosity: 0.01 };
  const c = new Cloth(json);
  c.v.set([0, 1, 0, 0, 0, 0]);
  c.step(1);
  // v_a' = 1 − h/m · 0.1 = 1 − 0.002; v_b' = +0.002; momentum is kept.
  close(c.v[1], 0.998, 1e-7, 'v_a');
  close(c.v[4], 0.002, 1e-7, 'v_b');
  close(c.v[1] + c.v[4], 1, 1e-7, 'momentum');
  // Without it a spring at rest length does nothing across itself.
  const plain = new Cloth(pair({ k: 10, b: 0, len: 1 }));
  plain.v.set([0, 1, 0, 0, 0, 0]);
  plain.step(1);
  assert.equal(plain.v[1], 1);
  // It counts as damping β k along the spring in the stability number: γ = (2 (b + β k) + c) / m.
  close(c.getStability().number, 0.01 * 0.01 * (20 / 0.5) + 2 * 0.01 * ((2 * 0.1) / 0.5), 1e-9, 'number');
  // A viscosity needs the /3 tag, and /3 a viscosity.
  assert.throws(() => new Cloth({ ...json, format: 'springtime-surrogate/1' }), /viscosity/);
  assert.throws(() => new Cloth({ ...pair(), format: 'springtime-surrogate/3' }), /viscosity/);
  assert.throws(() => new Cloth({ ...json, viscosity: -1 }), /viscosity/);
});

test('a damped spring stretched and let go comes to rest at its rest length', () => {
  const c = new Cloth(pair({ k: 10, b: 2, len: 1.5, frameDt: 0.001 }));
  c.step(5000);
  close(c.x[3] - c.x[0], 1, 1e-4, 'length');
  close(c.v[3], 0, 1e-4, 'v_b');
});

test('a pinned particle stays put and moves nothing but its spring', () => {
  const c = new Cloth(pair({ gravity: [0, 0, -9.81], pinned: [0] }));
  for (let j = 0; j < 100; j++) c.step(1);
  assert.deepEqual(Array.from(c.x.slice(0, 3)), [0, 0, 0]);
  assert.deepEqual(Array.from(c.v.slice(0, 3)), [0, 0, 0]);
  assert.ok(c.x[5] < -0.01, 'the free end falls');
});

test('Rayleigh damping slows every particle by c/m per unit time', () => {
  // Two particles at rest length moving together: no spring force; v' = v − h/m · c v.
  const c = new Cloth(pair({ len: 1, rayleigh: 0.1 }));
  c.v.set([1, 0, 0, 1, 0, 0]);
  c.step(1);
  const expect = fr(1 - fr(fr(0.01 / 0.5) * fr(0.1)));
  assert.equal(c.v[0], expect);
  close(c.v[0], 0.998, 1e-7, 'v');
  close(c.x[0], 0.01 * 0.998, 1e-9, 'x');
});

test('gravity: free fall by semi-implicit Euler', () => {
  // v_n = n h g, x_n = h² g n(n+1)/2.
  const c = new Cloth(pair({ len: 1, gravity: [0, 0, -10] }));
  c.step(10);
  close(c.v[2], -1, 1e-5, 'v_z');
  close(c.x[2], -0.01 * 0.01 * 10 * 55, 1e-6, 'z');
  assert.equal(c.x[2], c.x[5]);
});

test('substeps split the frame and a pinned path is followed at constant velocity', () => {
  const frameDt = 0.01;
  const c = new Cloth(pair({ len: 1, k: 0, substeps: 4, frameDt, pinned: [0] }));
  assert.equal(c.h, fr(0.0025));
  // Pin 0 moves 0.1 m along y per frame.
  const path = [];
  for (let j = 0; j <= 3; j++) path.push(0, 0.1 * j, 0);
  c.setPinPath(path);
  c.step(1);
  close(c.x[1], 0.1, 1e-7, 'pin at the end of frame 1');
  close(c.v[1], 0.1 / frameDt, 1e-4, 'pin velocity');
  c.step(1);
  close(c.x[1], 0.2, 1e-7, 'frame 2');
  c.step(5);
  close(c.x[1], 0.3, 1e-7, 'held at the last frame');
  assert.equal(c.v[1], 0, 'at rest once held');
  // Within a frame the pin's substep targets interpolate: after 1 substep of frame 1 → 0.025.
  const d = new Cloth(pair({ len: 1, k: 0, substeps: 4, frameDt, pinned: [0] }));
  d.setPinPath(path);
  const seen = [];
  const integrate = d.integrate.bind(d);
  d.integrate = (target) => {
    integrate(target);
    seen.push(d.x[1]);
  };
  d.step(1);
  seen.forEach((y, i) => close(y, 0.025 * (i + 1), 1e-7, 'substep ' + (i + 1)));
});

test('curvature elements push a bent triple straight (−κe, 2κe, −κe)', () => {
  const json = {
    ...pair({ len: 1, k: 0 }),
    format: 'springtime-surrogate/2',
    masses: [0.5, 0.5, 0.5],
    rest_positions: [[0, 0, 0], [1, 0, 0], [2, 0, 0]],
    curvature: [[0, 1, 2]],
    curvature_k: [3],
  };
  const c = new Cloth(json);
  c.x[4] = 0.1; // lift the middle particle: e = x_0 − 2 x_1 + x_2 = (0, −0.2, 0)
  c.forces(c.x, c.v, c.f);
  close(c.f[1], 0.6, 1e-6, 'F_0 = −κ e');
  close(c.f[4], -1.2, 1e-6, 'F_1 = 2κ e');
  close(c.f[7], 0.6, 1e-6, 'F_2 = −κ e');
});

test('particle masses: each force is divided by the relative mass m_i / m', () => {
  // Masses 0.25 and 0.75, mean 0.5: the spring force ±5 N becomes 5/0.5 = 10 on a and −5/1.5 on b.
  const json = { ...pair(), masses: [0.25, 0.75], mass: 0.5 };
  const c = new Cloth(json);
  c.forces(c.x, c.v, c.f);
  close(c.f[0], 10, 1e-5, 'F_a');
  close(c.f[3], -5 / 1.5, 1e-5, 'F_b');
  // The accelerations are F/m_i: the momentum change sums to zero.
  c.step(1);
  close(0.25 * c.v[0] + 0.75 * c.v[3], 0, 1e-7, 'momentum');
});

test('reset goes back to the rest state with the exported pins', () => {
  const c = new Cloth(pair({ gravity: [0, 0, -9.81], pinned: [0] }));
  c.step(50);
  c.reset();
  assert.deepEqual(Array.from(c.x), [0, 0, 0, 1.5, 0, 0]);
  assert.deepEqual(Array.from(c.v), [0, 0, 0, 0, 0, 0]);
  assert.deepEqual(c.pinnedList(), [0]);
  assert.equal(c.time, 0);
});

test('dragging a particle moves it like a pin, at most dragSpeed per second', () => {
  const c = new Cloth(pair({ len: 1, k: 10, frameDt: 0.001, pinned: [0] }));
  c.dragSpeed = 1;
  c.drag(0, [0, 0, 0.05]);
  c.step(10);
  close(c.x[2], 0.01, 1e-7, 'moved 1 m/s · 10 ms');
  c.step(100);
  close(c.x[2], 0.05, 1e-7, 'reached the target');
  c.release(0);
  c.step(10);
  close(c.x[2], 0.05, 1e-7, 'a released pin stays where it was left');
  assert.ok(c.x[5] > 0, 'the spring pulled the free end up');
});

test('a particle resting on the floor sinks about g/κ into the contact layer', () => {
  const c = new Cloth(pair({ len: 1, gravity: [0, 0, -9.81], frameDt: 0.001 }));
  c.setColliders([sim.ground(0, 0.5)], { thickness: 0.01, stiffness: 2.5e4, damping: 250 });
  c.step(3000);
  const depth = 0.01 - c.x[2];
  close(depth, 9.81 / 2.5e4, 1e-5, 'depth in the layer');
  close(c.v[2], 0, 1e-4, 'at rest');
});

test('friction holds a particle on a slope below the friction angle', () => {
  // A tilted "gravity" of slope 0.3 against μ = 0.5: static friction stops the sliding.
  const c = new Cloth(pair({ len: 1, k: 0, gravity: [3, 0, -10], frameDt: 0.001 }));
  c.setColliders([sim.ground(0, 0.5)], { thickness: 0.01, stiffness: 2.5e4, damping: 250 });
  c.step(2000);
  const x = c.x[0];
  c.step(1000);
  close(c.x[0], x, 1e-5, 'no sliding');
});

test('the stability number is computed as springtime does for a uniform pair', () => {
  // One spring along x between equal masses: λ_max(k u uᵀ on the incidence) = 2k.
  const c = new Cloth(pair({ k: 10, b: 1, len: 1, rayleigh: 0.1, frameDt: 0.01 }));
  const st = c.getStability();
  const omega2 = 20 / 0.5;
  const gamma = (2 + 0.1) / 0.5;
  close(st.number, 0.01 * 0.01 * omega2 + 2 * 0.01 * gamma, 1e-9, 'number');
  assert.equal(st.source, 'computed');
  const given = new Cloth({ ...pair(), stability: { number: 1.25, limit: 4 } }).getStability();
  assert.equal(given.number, 1.25);
});

test('an older surrogate.json without frame_dt steps at its dt; a bad one is refused by key', () => {
  const j = pair();
  delete j.frame_dt;
  delete j.substeps;
  delete j.mass;
  const c = new Cloth(j);
  assert.equal(c.frameDt, 0.01);
  assert.equal(c.substeps, 1);
  assert.equal(c.mass, 0.5);
  assert.throws(() => new Cloth({ ...pair(), format: 'other' }), /format/);
  assert.throws(() => new Cloth({ ...pair(), k: [] }), /`k`/);
  assert.throws(() => new Cloth({ ...pair(), springs: [[0, 5]] }), /spring/);
});

test('bench leaves the state as it was', () => {
  const c = new Cloth(pair({ gravity: [0, 0, -9.81] }));
  c.step(3);
  const x = Array.from(c.x);
  const r = c.bench(0.05);
  assert.ok(r.ratio > 0 && r.frames > 0);
  assert.deepEqual(Array.from(c.x), x);
  assert.equal(c.frame, 3);
});
