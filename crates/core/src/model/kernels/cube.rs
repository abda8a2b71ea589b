//! The fused spring ops on Burn's CubeCL backend (`Cube`: wgpu here; CUDA and the other CubeCL
//! runtimes are the same type, chosen by the device).
//!
//! No float atomics (neither portable on wgpu nor deterministic): every output element has
//! one owner thread that gathers what it needs.
//! - **Forward** (one launch per step): one thread per clip and particle walks the particle's
//!   springs in a CSR incidence list, computes each spring's force (Eq. 4) itself, sums them
//!   (Eq. 2), scales by the particle's force scale and, for a step, integrates (Eq. 5) with the
//!   pins. Each spring's force is computed by both endpoints: twice the arithmetic of a
//!   per-spring pass, but no scatter and no second launch.
//! - **Backward** (four launches): the upstream gradient `G` per particle (for a step, through
//!   the integrator, as in [`super::cpu`]); `∂ℓ/∂x`, `∂ℓ/∂v` per particle by the same CSR
//!   gather; `∂ℓ/∂k`, `∂ℓ/∂b` per spring and chunk of [`CLIPS_PER_THREAD`] clips; then one
//!   thread per spring sums its chunks.
//!
//! The kernels run in f32 (the backend's float type); the spring graph is uploaded once per
//! device and kept with the [`HostGraph`].

use std::sync::{Arc, Mutex};

use burn::tensor::{DType, Shape};
use burn_cubecl::cubecl;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};
use cubecl::prelude::*;
use cubecl::server::Handle;
use cubecl::{CubeDim, calculate_cube_count_elemwise};

use super::segment::{SegmentBackend, Segments, select_rows, sum_by_select_assign};
use super::{
    HostGraph, RolloutInputs, RolloutKernels, RolloutParams, RolloutTape, SpringBackend,
    SpringGrads, SpringInputs, StepParams, StepPins,
};

/// Clips summed by one thread of the parameter-gradient kernel.
pub(crate) const CLIPS_PER_THREAD: usize = 16;

/// The spring graph on one CubeCL device.
#[derive(Debug)]
pub(crate) struct DeviceGraph {
    /// Endpoints `a, b` of every spring, `[2S]` u32.
    ends: Handle,
    /// Rest lengths `[S]` f32.
    rest_length: Handle,
    /// CSR offsets into `incidence`, `[P + 1]` u32.
    offsets: Handle,
    /// `2 s + side` for every spring end, grouped by particle (side 0: the spring's first
    /// endpoint, which receives `+f`), `[2S]` u32.
    incidence: Handle,
    /// Force scale per particle (1 for equal masses), `[P]` f32.
    scale: Handle,
    springs: usize,
    particles: usize,
}

/// Device copies of a host structure (a [`HostGraph`], [`Segments`]), one per CubeCL device it
/// has run on.
pub(crate) struct CubeCache<T>(Mutex<Vec<(CubeDevice, Arc<T>)>>);

impl<T> CubeCache<T> {
    /// The copy on `device`, made by `upload` on first use.
    fn get(&self, device: &CubeDevice, upload: impl FnOnce() -> T) -> Arc<T> {
        let mut cache = self.0.lock().expect("cube device cache");
        if let Some((_, g)) = cache.iter().find(|(d, _)| d == device) {
            return g.clone();
        }
        let g = Arc::new(upload());
        cache.push((device.clone(), g.clone()));
        g
    }
}

impl<T> Default for CubeCache<T> {
    fn default() -> Self {
        Self(Mutex::new(Vec::new()))
    }
}

impl<T> Clone for CubeCache<T> {
    /// A clone starts empty: device buffers are cheap to upload again and belong to one graph.
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl<T> PartialEq for CubeCache<T> {
    /// Caches never make two graphs differ.
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl<T> std::fmt::Debug for CubeCache<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("CubeCache")
    }
}

/// The graph's buffers on `device`, uploaded on first use.
fn device_graph(graph: &HostGraph, device: &CubeDevice) -> Arc<DeviceGraph> {
    graph.cube.get(device, || upload_graph(graph, device))
}

fn upload_graph(graph: &HostGraph, device: &CubeDevice) -> DeviceGraph {
    let client = device.client();
    let (s_count, p) = (graph.num_springs(), graph.particles);
    let ends: Vec<u32> = graph.ends.iter().flat_map(|&(a, b)| [a, b]).collect();
    let l0: Vec<f32> = graph.rest_length.iter().map(|&l| l as f32).collect();
    let mut counts = vec![0u32; p + 1];
    for &(a, b) in &graph.ends {
        counts[a as usize + 1] += 1;
        counts[b as usize + 1] += 1;
    }
    for i in 0..p {
        counts[i + 1] += counts[i];
    }
    let mut fill = counts.clone();
    let mut incidence = vec![0u32; 2 * s_count];
    for (s, &(a, b)) in graph.ends.iter().enumerate() {
        for (side, end) in [a, b].into_iter().enumerate() {
            incidence[fill[end as usize] as usize] = (2 * s + side) as u32;
            fill[end as usize] += 1;
        }
    }
    let scale: Vec<f32> = match &graph.force_scale {
        Some(s) => s.iter().map(|&v| v as f32).collect(),
        None => vec![1.0; p],
    };
    DeviceGraph {
        ends: client.create_from_slice(u32::as_bytes(&ends)),
        rest_length: client.create_from_slice(f32::as_bytes(&l0)),
        offsets: client.create_from_slice(u32::as_bytes(&counts)),
        incidence: client.create_from_slice(u32::as_bytes(&incidence)),
        scale: client.create_from_slice(f32::as_bytes(&scale)),
        springs: s_count,
        particles: p,
    }
}

impl DeviceGraph {
    fn arg(handle: &Handle, len: usize) -> BufferArg {
        // SAFETY: every handle above was created from a slice of exactly this length.
        unsafe { BufferArg::from_raw_parts(handle.clone(), len) }
    }
    fn ends(&self) -> BufferArg {
        Self::arg(&self.ends, 2 * self.springs)
    }
    fn rest_length(&self) -> BufferArg {
        Self::arg(&self.rest_length, self.springs)
    }
    fn offsets(&self) -> BufferArg {
        Self::arg(&self.offsets, self.particles + 1)
    }
    fn incidence(&self) -> BufferArg {
        Self::arg(&self.incidence, 2 * self.springs)
    }
    fn scale(&self) -> BufferArg {
        Self::arg(&self.scale, self.particles)
    }
}

/// `a[ib..ib + 3] − a[ia..ia + 3]`: a spring's vector from its first to its second end.
#[cube]
fn difference<F: Float>(a: &[F], ia: usize, ib: usize) -> (F, F, F) {
    (a[ib] - a[ia], a[ib + 1] - a[ia + 1], a[ib + 2] - a[ia + 2])
}

/// Entry `e` of the CSR incidence list: the spring `s`, whether the particle is its first
/// end, and the offsets of its two ends' coordinates in a clip starting at particle `base`.
#[cube]
fn incident(incidence: &[u32], ends: &[u32], e: usize, base: usize) -> (usize, bool, usize, usize) {
    let entry = usize::cast_from(incidence[e]);
    let s = entry / 2;
    let ia = (base + usize::cast_from(ends[2 * s])) * 3;
    let ib = (base + usize::cast_from(ends[2 * s + 1])) * 3;
    (s, entry % 2 == 0, ia, ib)
}

/// Spring forces on one particle of one clip (`item = clip · P + p`), scaled: Eqs. 4 and 2.
#[cube]
#[allow(clippy::too_many_arguments)]
fn gather_forces<F: Float>(
    x: &[F],
    v: &[F],
    k: &[F],
    b: &[F],
    ends: &[u32],
    l0: &[F],
    offsets: &[u32],
    incidence: &[u32],
    scale: &[F],
    item: usize,
    particles: usize,
) -> (F, F, F) {
    let p = item % particles;
    let base = item - p;
    let mut f0 = F::new(0.0);
    let mut f1 = F::new(0.0);
    let mut f2 = F::new(0.0);
    let start = usize::cast_from(offsets[p]);
    let end = usize::cast_from(offsets[p + 1]);
    for e in start..end {
        let (s, first, ia, ib) = incident(incidence, ends, e, base);
        let (d0, d1, d2) = difference::<F>(x, ia, ib);
        let (w0, w1, w2) = difference::<F>(v, ia, ib);
        let len2 = d0 * d0 + d1 * d1 + d2 * d2;
        let wd = w0 * d0 + w1 * d1 + w2 * d2;
        let inv = F::new(1.0) / F::sqrt(len2);
        let mut coef = k[s] * (F::new(1.0) - l0[s] * inv) + b[s] * wd * inv * inv;
        if !first {
            coef = -coef;
        }
        f0 += coef * d0;
        f1 += coef * d1;
        f2 += coef * d2;
    }
    let sc = scale[p];
    (f0 * sc, f1 * sc, f2 * sc)
}

/// The constants of a step: `h`, `h/m`, the Rayleigh `c` and the weight `m g`.
#[derive(CubeType, CubeLaunch, Clone, Copy)]
pub(crate) struct StepConsts {
    h: f32,
    hm: f32,
    c: f32,
    mg0: f32,
    mg1: f32,
    mg2: f32,
}

/// Semi-implicit Euler (Eq. 5) of one component `i` with spring force and weight `s`; pinned
/// particles take their prescribed state. Writes `x'`, `v'`, `f` at `i`, `n + i`, `2n + i`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn integrate<F: Float>(
    x: &[F],
    v: &[F],
    pin_x: &[F],
    pin_v: &[F],
    out: &mut [F],
    i: usize,
    n: usize,
    s: F,
    h: F,
    hm: F,
    c: F,
    pinned: bool,
) {
    let f = s - c * v[i];
    let vn = v[i] + hm * f;
    let xn = x[i] + h * vn;
    if pinned {
        out[i] = pin_x[i];
        out[n + i] = pin_v[i];
    } else {
        out[i] = xn;
        out[n + i] = vn;
    }
    out[2 * n + i] = f;
}

/// Spring forces `[B, P, 3]`, or (`step`) one semi-implicit Euler step writing `x'`, `v'` and
/// the net force `f` as `[3, B, P, 3]`.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn forward_kernel<F: Float>(
    x: &[F],
    v: &[F],
    k: &[F],
    b: &[F],
    pinned: &[F],
    pin_x: &[F],
    pin_v: &[F],
    ends: &[u32],
    l0: &[F],
    offsets: &[u32],
    incidence: &[u32],
    scale: &[F],
    out: &mut [F],
    particles: usize,
    items: usize,
    consts: StepConsts,
    #[comptime] step: bool,
) {
    let item = ABSOLUTE_POS;
    if item >= items {
        terminate!();
    }
    let (s0, s1, s2) = gather_forces::<F>(
        x, v, k, b, ends, l0, offsets, incidence, scale, item, particles,
    );
    let i = item * 3;
    if step {
        let n = items * 3;
        let pinned_here = pinned[item] > F::new(0.0);
        let h = F::cast_from(consts.h);
        let hm = F::cast_from(consts.hm);
        let c = F::cast_from(consts.c);
        let w0 = s0 + F::cast_from(consts.mg0);
        let w1 = s1 + F::cast_from(consts.mg1);
        let w2 = s2 + F::cast_from(consts.mg2);
        integrate::<F>(x, v, pin_x, pin_v, out, i, n, w0, h, hm, c, pinned_here);
        integrate::<F>(x, v, pin_x, pin_v, out, i + 1, n, w1, h, hm, c, pinned_here);
        integrate::<F>(x, v, pin_x, pin_v, out, i + 2, n, w2, h, hm, c, pinned_here);
    } else {
        out[i] = s0;
        out[i + 1] = s1;
        out[i + 2] = s2;
    }
}

/// The upstream gradient of the spring forces `G·scale` per particle, and the gradients that
/// do not go through the springs as the start of `gx`, `gv`.
///
/// Forces (`!step`): `grad = ∂ℓ/∂F` `[B, P, 3]`, `G = grad`, `gx = gv = 0`.
/// Step: `grad = ∂ℓ/∂(x', v', f)` `[3, B, P, 3]`; `ḡx'' = free ∂ℓ/∂x'`,
/// `ḡv'' = free ∂ℓ/∂v' + h ḡx''`, `G = ∂ℓ/∂f + h/m ḡv''`, `gx = ḡx''`, `gv = ḡv'' − c G`.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn upstream_kernel<F: Float>(
    grad: &[F],
    pinned: &[F],
    scale: &[F],
    gs: &mut [F],
    gx: &mut [F],
    gv: &mut [F],
    particles: usize,
    items: usize,
    consts: StepConsts,
    #[comptime] step: bool,
) {
    let item = ABSOLUTE_POS;
    if item >= items {
        terminate!();
    }
    let sc = scale[item % particles];
    let i = item * 3;
    if step {
        let h = F::cast_from(consts.h);
        let hm = F::cast_from(consts.hm);
        let c = F::cast_from(consts.c);
        let n = items * 3;
        let free = pinned[item] <= F::new(0.0);
        #[unroll]
        for a in 0..3 {
            let mut gxx = F::new(0.0);
            let mut gvv = F::new(0.0);
            if free {
                gxx = grad[i + a];
                gvv = grad[n + i + a] + h * gxx;
            }
            let g = grad[2 * n + i + a] + hm * gvv;
            gs[i + a] = g * sc;
            gx[i + a] = gxx;
            gv[i + a] = gvv - c * g;
        }
    } else {
        #[unroll]
        for a in 0..3 {
            gs[i + a] = grad[i + a] * sc;
            gx[i + a] = F::new(0.0);
            gv[i + a] = F::new(0.0);
        }
    }
}

/// Adds `S_xᵀ G` to `gx` and `S_vᵀ G` to `gv` for one particle of one clip, from the scaled
/// upstream gradients `gs` of both ends of each of its springs.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn particle_backward_kernel<F: Float>(
    x: &[F],
    v: &[F],
    k: &[F],
    b: &[F],
    gs: &[F],
    ends: &[u32],
    l0: &[F],
    offsets: &[u32],
    incidence: &[u32],
    gx: &mut [F],
    gv: &mut [F],
    particles: usize,
    items: usize,
) {
    let item = ABSOLUTE_POS;
    if item >= items {
        terminate!();
    }
    let p = item % particles;
    let base = item - p;
    let mut ax0 = F::new(0.0);
    let mut ax1 = F::new(0.0);
    let mut ax2 = F::new(0.0);
    let mut av0 = F::new(0.0);
    let mut av1 = F::new(0.0);
    let mut av2 = F::new(0.0);
    let start = usize::cast_from(offsets[p]);
    let end = usize::cast_from(offsets[p + 1]);
    for e in start..end {
        let (s, first, ia, ib) = incident(incidence, ends, e, base);
        let (d0, d1, d2) = difference::<F>(x, ia, ib);
        let (w0, w1, w2) = difference::<F>(v, ia, ib);
        let (g0, g1, g2) = difference::<F>(gs, ib, ia);
        let len2 = d0 * d0 + d1 * d1 + d2 * d2;
        let wd = w0 * d0 + w1 * d1 + w2 * d2;
        let gd = g0 * d0 + g1 * d1 + g2 * d2;
        let inv = F::new(1.0) / F::sqrt(len2);
        let inv2 = inv * inv;
        let coef = k[s] * (F::new(1.0) - l0[s] * inv) + b[s] * wd * inv2;
        let a1 = k[s] * l0[s] * inv2 * inv - F::new(2.0) * b[s] * wd * inv2 * inv2;
        let a2 = b[s] * inv2;
        // ∂ℓ/∂d = c g + (g·d)(a1 d + a2 w), ∂ℓ/∂w = (g·d) a2 d; the second endpoint adds
        // them, the first subtracts them.
        let mut sign = F::new(1.0);
        if first {
            sign = F::new(-1.0);
        }
        ax0 += sign * (coef * g0 + gd * (a1 * d0 + a2 * w0));
        ax1 += sign * (coef * g1 + gd * (a1 * d1 + a2 * w1));
        ax2 += sign * (coef * g2 + gd * (a1 * d2 + a2 * w2));
        av0 += sign * gd * a2 * d0;
        av1 += sign * gd * a2 * d1;
        av2 += sign * gd * a2 * d2;
    }
    let i = item * 3;
    gx[i] += ax0;
    gx[i + 1] += ax1;
    gx[i + 2] += ax2;
    gv[i] += av0;
    gv[i + 1] += av1;
    gv[i + 2] += av2;
}

/// `∂ℓ/∂k`, `∂ℓ/∂b` of one spring summed over one chunk of clips: `partial[chunk, s]`.
#[cube(launch_unchecked)]
#[allow(clippy::too_many_arguments)]
fn spring_backward_kernel<F: Float>(
    x: &[F],
    v: &[F],
    gs: &[F],
    ends: &[u32],
    l0: &[F],
    pk: &mut [F],
    pb: &mut [F],
    particles: usize,
    springs: usize,
    clips: usize,
    chunks: usize,
    #[comptime] per_thread: usize,
) {
    let id = ABSOLUTE_POS;
    if id >= springs * chunks {
        terminate!();
    }
    let s = id % springs;
    let chunk = id / springs;
    let a = usize::cast_from(ends[2 * s]);
    let bb = usize::cast_from(ends[2 * s + 1]);
    let rest = l0[s];
    let mut dk = F::new(0.0);
    let mut db = F::new(0.0);
    let first = chunk * per_thread;
    let mut last = first + per_thread;
    if last > clips {
        last = clips;
    }
    for clip in first..last {
        let ia = (clip * particles + a) * 3;
        let ib = (clip * particles + bb) * 3;
        let (d0, d1, d2) = difference::<F>(x, ia, ib);
        let (w0, w1, w2) = difference::<F>(v, ia, ib);
        let (g0, g1, g2) = difference::<F>(gs, ib, ia);
        let len2 = d0 * d0 + d1 * d1 + d2 * d2;
        let wd = w0 * d0 + w1 * d1 + w2 * d2;
        let gd = g0 * d0 + g1 * d1 + g2 * d2;
        let inv = F::new(1.0) / F::sqrt(len2);
        dk += gd * (F::new(1.0) - rest * inv);
        db += gd * wd * inv * inv;
    }
    pk[id] = dk;
    pb[id] = db;
}

/// `out[s] = Σ_chunk partial[chunk, s]`, in chunk order (deterministic).
#[cube(launch_unchecked)]
fn sum_chunks_kernel<F: Float>(partial: &[F], out: &mut [F], springs: usize, chunks: usize) {
    let s = ABSOLUTE_POS;
    if s >= springs {
        terminate!();
    }
    let mut acc = F::new(0.0);
    for c in 0..chunks {
        acc += partial[c * springs + s];
    }
    out[s] = acc;
}

/// A contiguous f32 tensor's buffer.
fn arg(t: &CubeTensor) -> BufferArg {
    // SAFETY: `t` is contiguous (see `prepare`), so its buffer holds exactly its elements.
    unsafe { BufferArg::from_raw_parts(t.handle.clone(), t.meta.shape().num_elements()) }
}

/// `t` made contiguous, checked to be f32.
fn prepare(t: CubeTensor, what: &str) -> CubeTensor {
    assert!(
        t.dtype == DType::F32,
        "springtime's CubeCL kernels run in f32; {what} is {:?}",
        t.dtype
    );
    into_contiguous(t)
}

/// The batch and particle count of states `x` `[B, P, 3]`, after checking that every tensor
/// the kernels index holds what they read: the kernels launch unchecked, so a mismatch would
/// read or write out of bounds on the device. `per_item` pairs a tensor with the values it
/// must hold per (clip, particle).
fn check_shapes(
    x: &CubeTensor,
    k: &CubeTensor,
    b: &CubeTensor,
    per_item: &[(&CubeTensor, usize, &str)],
    graph: &HostGraph,
) -> (usize, usize) {
    let dims = x.meta.shape().to_vec();
    assert!(
        dims.len() == 3 && dims[1] == graph.particles && dims[2] == 3,
        "states must be [B, {}, 3], are {dims:?}",
        graph.particles
    );
    let s = graph.num_springs();
    for (t, name) in [(k, "k"), (b, "b")] {
        let n = t.meta.shape().num_elements();
        assert_eq!(
            n, s,
            "{name} must hold one value per spring ({s}), holds {n}"
        );
    }
    let items = dims[0] * dims[1];
    for &(t, per, name) in per_item {
        let n = t.meta.shape().num_elements();
        assert_eq!(
            n,
            items * per,
            "{name} must hold {per} values per clip and particle"
        );
    }
    (dims[0], dims[1])
}

fn empty(like: &CubeTensor, shape: Vec<usize>) -> CubeTensor {
    empty_device_contiguous_dtype(
        like.client.clone(),
        like.device.clone(),
        Shape::from(shape),
        DType::F32,
    )
}

/// The step's constants as kernel arguments (zeros for the force-only kernels, which do not
/// read them).
fn step_constants(params: Option<&StepParams>) -> StepConstsLaunch {
    let (h, m, c, g) = match params {
        Some(p) => (p.h, p.mass, p.rayleigh, p.gravity),
        None => (0.0, 1.0, 0.0, [0.0; 3]),
    };
    StepConstsLaunch::new(
        h as f32,
        (h / m) as f32,
        c as f32,
        (g[0] * m) as f32,
        (g[1] * m) as f32,
        (g[2] * m) as f32,
    )
}

fn launch_dims(t: &CubeTensor, units: usize) -> (CubeCount, CubeDim) {
    let dim = CubeDim::new(&t.client, units);
    (calculate_cube_count_elemwise(&t.client, units, dim), dim)
}

/// The forward kernel: forces `[B, P, 3]`, or with `pins` (a step) the stacked `[3, B, P, 3]`.
fn forward(
    s: SpringInputs<CubeBackend>,
    pins: Option<(StepPins<CubeBackend>, StepParams)>,
    graph: &HostGraph,
) -> CubeTensor {
    let (x, v) = (prepare(s.x, "x"), prepare(s.v, "v"));
    let (k, b) = (prepare(s.k, "k"), prepare(s.b, "b"));
    let pins = pins.map(|(pins, params)| {
        (
            prepare(pins.pinned, "pinned"),
            prepare(pins.x, "pin_x"),
            prepare(pins.v, "pin_v"),
            params,
        )
    });
    let mut per_item = vec![(&v, 3, "v")];
    if let Some((pinned, pin_x, pin_v, _)) = &pins {
        per_item.extend([
            (pinned, 1, "pinned"),
            (pin_x, 3, "pin_x"),
            (pin_v, 3, "pin_v"),
        ]);
    }
    let (batch, particles) = check_shapes(&x, &k, &b, &per_item, graph);
    let g = device_graph(graph, &x.device);
    let items = batch * particles;
    let step = pins.is_some();
    let out_shape = if step {
        vec![3, batch, particles, 3]
    } else {
        vec![batch, particles, 3]
    };
    let out = empty(&x, out_shape);
    let (pinned, pin_x, pin_v, consts) = match pins {
        Some((pinned, pin_x, pin_v, params)) => {
            (pinned, pin_x, pin_v, step_constants(Some(&params)))
        }
        // Unread without `step`: any buffers do.
        None => (x.clone(), x.clone(), x.clone(), step_constants(None)),
    };
    let (count, dim) = launch_dims(&x, items);
    // SAFETY: every buffer holds what the kernel indexes: states `items · 3`, pins `items`,
    // per-spring values `S`, graph arrays as uploaded, the output `items · 3` (times 3 for a
    // step); the thread guard stops at `items`.
    unsafe {
        forward_kernel::launch_unchecked::<f32>(
            &x.client,
            count,
            dim,
            arg(&x),
            arg(&v),
            arg(&k),
            arg(&b),
            arg(&pinned),
            arg(&pin_x),
            arg(&pin_v),
            g.ends(),
            g.rest_length(),
            g.offsets(),
            g.incidence(),
            g.scale(),
            arg(&out),
            particles,
            items,
            consts,
            step,
        )
    };
    out
}

/// The backward of [`forward`]: `∂ℓ/∂x`, `∂ℓ/∂v`, `∂ℓ/∂k`, `∂ℓ/∂b`.
fn backward(
    s: SpringInputs<CubeBackend>,
    grad: CubeTensor,
    step: Option<(CubeTensor, StepParams)>,
    graph: &HostGraph,
) -> SpringGrads<CubeBackend> {
    let (x, v) = (prepare(s.x, "x"), prepare(s.v, "v"));
    let (k, b) = (prepare(s.k, "k"), prepare(s.b, "b"));
    let grad = prepare(grad, "the upstream gradient");
    let step = step.map(|(pinned, params)| (prepare(pinned, "pinned"), params));
    let mut per_item = vec![(&v, 3, "v")];
    match &step {
        Some((pinned, _)) => per_item.extend([(pinned, 1, "pinned"), (&grad, 9, "the gradient")]),
        None => per_item.push((&grad, 3, "the gradient")),
    }
    let (batch, particles) = check_shapes(&x, &k, &b, &per_item, graph);
    let g = device_graph(graph, &x.device);
    let items = batch * particles;
    let state = vec![batch, particles, 3];
    let (gs, gx, gv) = (
        empty(&x, state.clone()),
        empty(&x, state.clone()),
        empty(&x, state),
    );
    let is_step = step.is_some();
    let (pinned, consts) = match step {
        Some((pinned, params)) => (pinned, step_constants(Some(&params))),
        None => (x.clone(), step_constants(None)),
    };
    let (count, dim) = launch_dims(&x, items);
    // SAFETY (all launches): buffers as in `forward`; `gs`, `gx`, `gv` hold `items · 3`,
    // the partial sums `chunks · S`, the outputs `S`; each kernel guards its thread count.
    unsafe {
        upstream_kernel::launch_unchecked::<f32>(
            &x.client,
            count.clone(),
            dim,
            arg(&grad),
            arg(&pinned),
            g.scale(),
            arg(&gs),
            arg(&gx),
            arg(&gv),
            particles,
            items,
            consts,
            is_step,
        );
        particle_backward_kernel::launch_unchecked::<f32>(
            &x.client,
            count,
            dim,
            arg(&x),
            arg(&v),
            arg(&k),
            arg(&b),
            arg(&gs),
            g.ends(),
            g.rest_length(),
            g.offsets(),
            g.incidence(),
            arg(&gx),
            arg(&gv),
            particles,
            items,
        );
    }
    let springs = g.springs;
    let chunks = batch.div_ceil(CLIPS_PER_THREAD);
    let (pk, pb) = (
        empty(&x, vec![chunks, springs]),
        empty(&x, vec![chunks, springs]),
    );
    let (count, dim) = launch_dims(&x, chunks * springs);
    unsafe {
        spring_backward_kernel::launch_unchecked::<f32>(
            &x.client,
            count,
            dim,
            arg(&x),
            arg(&v),
            arg(&gs),
            g.ends(),
            g.rest_length(),
            arg(&pk),
            arg(&pb),
            particles,
            springs,
            batch,
            chunks,
            CLIPS_PER_THREAD,
        );
    }
    let (gk, gb) = (empty(&x, vec![springs]), empty(&x, vec![springs]));
    let (count, dim) = launch_dims(&x, springs);
    unsafe {
        sum_chunks_kernel::launch_unchecked::<f32>(
            &x.client,
            count.clone(),
            dim,
            arg(&pk),
            arg(&gk),
            springs,
            chunks,
        );
        sum_chunks_kernel::launch_unchecked::<f32>(
            &x.client,
            count,
            dim,
            arg(&pb),
            arg(&gb),
            springs,
            chunks,
        );
    }
    SpringGrads {
        x: gx,
        v: gv,
        k: gk,
        b: gb,
    }
}

impl SpringBackend for CubeBackend {
    fn spring_forces(s: SpringInputs<Self>, graph: Arc<HostGraph>) -> CubeTensor {
        forward(s, None, &graph)
    }

    fn spring_forces_backward(
        s: SpringInputs<Self>,
        grad: CubeTensor,
        graph: Arc<HostGraph>,
    ) -> SpringGrads<Self> {
        backward(s, grad, None, &graph)
    }

    fn cloth_step(
        s: SpringInputs<Self>,
        pins: StepPins<Self>,
        graph: Arc<HostGraph>,
        params: StepParams,
    ) -> CubeTensor {
        forward(s, Some((pins, params)), &graph)
    }

    fn cloth_step_backward(
        s: SpringInputs<Self>,
        pinned: CubeTensor,
        grad: CubeTensor,
        graph: Arc<HostGraph>,
        params: StepParams,
    ) -> SpringGrads<Self> {
        backward(s, grad, Some((pinned, params)), &graph)
    }

    fn rollout_loss(
        _inputs: RolloutInputs<Self>,
        _graph: Arc<HostGraph>,
        _params: RolloutParams,
    ) -> CubeTensor {
        unimplemented!("{WHOLE_ROLLOUT}")
    }
}

/// Why [`RolloutKernels`] is not implemented on Cube.
const WHOLE_ROLLOUT: &str = "the whole-rollout op runs on the CPU backends only; on a CubeCL \
device the rollout is a sequence of fused steps (SpringGraph::fused_rollout is false there)";

impl RolloutKernels for CubeBackend {
    fn rollout_forward(
        _inputs: &RolloutInputs<Self>,
        _graph: &HostGraph,
        _params: RolloutParams,
    ) -> (CubeTensor, RolloutTape) {
        unimplemented!("{WHOLE_ROLLOUT}")
    }

    fn rollout_backward(
        _inputs: &RolloutInputs<Self>,
        _graph: &HostGraph,
        _params: RolloutParams,
        _tape: &RolloutTape,
        _w: [f64; 3],
    ) -> (CubeTensor, CubeTensor) {
        unimplemented!("{WHOLE_ROLLOUT}")
    }
}

/// A [`Segments`] CSR list on one CubeCL device.
#[derive(Debug)]
pub(crate) struct CubeSegments {
    /// `[N + 1]` u32.
    offsets: Handle,
    /// `[E]` u32.
    order: Handle,
    segments: usize,
    entries: usize,
}

/// `out[n, l] = Σ values[order[j], l]` over `j ∈ offsets[n]..offsets[n + 1]`: one thread per
/// output element, its segment summed in order (deterministic, no atomics).
#[cube(launch_unchecked)]
fn segment_sum_kernel<F: Float>(
    values: &[F],
    offsets: &[u32],
    order: &[u32],
    out: &mut [F],
    width: usize,
    items: usize,
) {
    let item = ABSOLUTE_POS;
    if item >= items {
        terminate!();
    }
    let n = item / width;
    let l = item % width;
    let mut acc = F::new(0.0);
    let start = usize::cast_from(offsets[n]);
    let end = usize::cast_from(offsets[n + 1]);
    for j in start..end {
        acc += values[usize::cast_from(order[j]) * width + l];
    }
    out[item] = acc;
}

impl SegmentBackend for CubeBackend {
    fn segment_sum(values: CubeTensor, owner: CubeTensor, segments: Arc<Segments>) -> CubeTensor {
        if segments.num_entries() == 0 {
            // Zeros; the kernel's buffers would be empty.
            return sum_by_select_assign::<Self>(values, owner, &segments);
        }
        let values = prepare(values, "the values to sum");
        let dims = values.meta.shape().to_vec();
        assert!(
            dims.len() == 2 && dims[0] == segments.num_entries(),
            "segment_sum: values must be [{}, L], are {dims:?}",
            segments.num_entries()
        );
        let device = values.device.clone();
        let g = segments.cube.get(&device, || {
            let client = device.client();
            CubeSegments {
                offsets: client.create_from_slice(u32::as_bytes(segments.offsets())),
                order: client.create_from_slice(u32::as_bytes(segments.order())),
                segments: segments.num_segments(),
                entries: segments.num_entries(),
            }
        });
        let width = dims[1];
        let items = g.segments * width;
        let out = empty(&values, vec![g.segments, width]);
        if items == 0 {
            return out;
        }
        let (count, dim) = launch_dims(&values, items);
        // SAFETY: `values` holds `E · width` (checked above), the CSR arrays hold `N + 1` and
        // `E` entries with every `order[j] < E` and offsets within `0..=E` (built by
        // `Segments::new`), `out` holds `N · width`; the thread guard stops at `items`.
        unsafe {
            segment_sum_kernel::launch_unchecked::<f32>(
                &values.client,
                count,
                dim,
                arg(&values),
                DeviceGraph::arg(&g.offsets, g.segments + 1),
                DeviceGraph::arg(&g.order, g.entries),
                arg(&out),
                width,
                items,
            )
        };
        out
    }

    fn gather_rows(x: CubeTensor, owner: CubeTensor, _segments: Arc<Segments>) -> CubeTensor {
        select_rows::<Self>(x, owner)
    }
}
