//! The mass-spring surrogate: per-spring stiffness `k` and damping `b` (paper §3.2).

use std::sync::Arc;

use burn::module::{Module, Param};
use burn::tensor::{Device, Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::kernels::segment::{DeviceSegments, Segments};
use super::kernels::{self, HostGraph};
use crate::cloth::Topology;

/// Which implementation computes the spring forces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Kernel {
    /// One fused kernel with a hand-written backward ([`kernels::spring_forces`]).
    #[default]
    Fused,
    /// Burn tensor ops ([`SpringGraph::spring_forces_reference`]): gathers, Eq. 4, a scatter-add.
    Reference,
}

/// The spring network's constant tensors: endpoints and rest lengths.
#[derive(Module, Debug)]
pub struct SpringGraph {
    /// First endpoint `a` of every spring, `[S]`.
    pub ia: Tensor<1, Int>,
    /// Second endpoint `b` of every spring, `[S]`.
    pub ib: Tensor<1, Int>,
    /// `[ia, ib]`, `[2S]`: the signed incidence matrix of Eq. 2 as a scatter index
    /// (`+f` goes to the first half, `-f` to the second).
    pub ends: Tensor<1, Int>,
    /// Rest length `l0` of every spring, `[S]`.
    pub rest_length: Tensor<1>,
    /// Number of particles `P`.
    pub num_particles: usize,
    /// Number of springs `S`.
    pub num_springs: usize,
    /// `1 / w` per particle, `[1, P, 1]`, for relative masses `w`
    /// ([`Topology::mass_weight`]); `None`: equal masses.
    pub force_scale: Option<Tensor<3>>,
    /// 1 on every shear spring ([`crate::cloth::SpringFamily::Shear`]), 0 elsewhere, `[S]`: the
    /// springs [`SpringGraph::compression_forces`] softens.
    pub shear: Tensor<1>,
    /// The same springs on the host, for the fused kernels.
    #[module(skip)]
    pub host: Arc<HostGraph>,
    /// Which implementation [`SpringNet::forces`] uses.
    #[module(skip)]
    pub kernel: Kernel,
    /// Where the fused kernels run on this graph's device.
    #[module(skip)]
    pub fused_on: FusedOn,
}

/// Which fused kernels a device has.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FusedOn {
    /// The CPU backends (`flex`, `ndarray`): forces, step and the whole-rollout op.
    Host,
    /// A CubeCL device (`wgpu`): forces and step.
    Cube,
    /// None: tensor ops only.
    Nowhere,
}

impl FusedOn {
    /// The fused kernels of `device` (with or without autodiff).
    pub fn of(device: &Device) -> Self {
        use burn::backend::DispatchDevice;
        match device.clone().inner().as_dispatch() {
            DispatchDevice::Flex(_) | DispatchDevice::NdArray(_) => Self::Host,
            #[cfg(feature = "wgpu")]
            DispatchDevice::Cube(_) => Self::Cube,
            #[allow(unreachable_patterns)]
            _ => Self::Nowhere,
        }
    }
}

impl SpringGraph {
    /// Uploads the topology's springs to `device`.
    pub fn new(topology: &Topology, device: &Device) -> Self {
        let s = topology.num_springs();
        let ia: Vec<i64> = topology.springs.iter().map(|e| e[0] as i64).collect();
        let ib: Vec<i64> = topology.springs.iter().map(|e| e[1] as i64).collect();
        let ends: Vec<i64> = ia.iter().chain(&ib).copied().collect();
        let l0 = topology.rest_length.clone();
        let scale = topology.force_scale();
        let shear: Vec<bool> = topology
            .family
            .iter()
            .map(|f| *f == crate::cloth::SpringFamily::Shear)
            .collect();
        let int = |v: Vec<i64>| {
            Tensor::<1, Int>::from_data(TensorData::new(v.clone(), [v.len()]), device)
        };
        Self {
            ia: int(ia),
            ib: int(ib),
            ends: int(ends),
            rest_length: Tensor::from_data(TensorData::new(l0, [s]), device),
            shear: Tensor::from_data(
                TensorData::new(
                    shear
                        .iter()
                        .map(|&m| if m { 1.0f32 } else { 0.0 })
                        .collect(),
                    [s],
                ),
                device,
            ),
            num_particles: topology.num_particles(),
            num_springs: s,
            force_scale: scale.clone().map(|f| {
                let p = f.len();
                Tensor::<1>::from_data(TensorData::new(f, [p]), device).reshape([1, p, 1])
            }),
            host: Arc::new(
                HostGraph::new(
                    &topology.springs,
                    &topology.rest_length,
                    topology.num_particles(),
                )
                .with_force_scale(scale)
                .with_curvature(&topology.curvature)
                .with_shear(&shear),
            ),
            kernel: Kernel::Fused,
            fused_on: FusedOn::of(device),
        }
    }
}

impl SpringGraph {
    /// Whether the fused spring-force op runs here (for the springs; on the CPU also for the
    /// curvature elements).
    pub fn fused_forces(&self) -> bool {
        self.kernel == Kernel::Fused && self.fused_on != FusedOn::Nowhere
    }

    /// Whether the fused ops take the curvature elements along with the springs: the CPU
    /// kernels do; the CubeCL kernels know springs only, so there the elements' forces are
    /// tensor ops beside the fused spring forces, and the step is tensor ops.
    pub(crate) fn fused_curvature(&self) -> bool {
        self.fused_forces() && (self.fused_on == FusedOn::Host || self.host.num_triples() == 0)
    }

    /// Whether the fused whole-rollout op ([`kernels::rollout_loss`]) runs here.
    pub(crate) fn fused_rollout(&self) -> bool {
        self.kernel == Kernel::Fused && self.fused_on == FusedOn::Host
    }

    /// Internal spring forces on every particle as Burn tensor ops (two gathers per state, Eq. 4,
    /// one scatter-add): the reference the fused kernel is tested against, and what
    /// [`SpringNet::forces`] runs where the fused kernel does not.
    ///
    /// `x`, `v`: positions and velocities `[B, P, 3]`; `k`, `b`: `[S]`. Returns `[B, P, 3]`.
    /// For spring `s = (a, b)` with `d = x_b − x_a`, `w = v_b − v_a`:
    /// `f_s = k (|d| − l0) d/|d| + b (w·d) d/|d|²` acts on `a` and `−f_s` on `b`, so the forces sum
    /// to zero by construction (Newton's third law). On a graph with particle masses
    /// ([`SpringGraph::force_scale`]) each particle's force is then divided by its relative mass
    /// (the mass-weighted sum, the momentum change, stays zero).
    pub fn spring_forces_reference(
        &self,
        x: Tensor<3>,
        v: Tensor<3>,
        k: Tensor<1>,
        b: Tensor<1>,
    ) -> Tensor<3> {
        let [batch, p, _] = x.dims();
        let s = self.num_springs;
        let d = x.clone().select(1, self.ib.clone()) - x.select(1, self.ia.clone());
        let w = v.clone().select(1, self.ib.clone()) - v.select(1, self.ia.clone());
        let len2 = (d.clone() * d.clone()).sum_dim(2); // [B, S, 1]
        let inv_len = len2.sqrt().recip();
        let l0 = self.rest_length.clone().reshape([1, s, 1]);
        let elastic = k.reshape([1, s, 1]) * (l0 * inv_len.clone()).neg().add_scalar(1.0);
        let damping = b.reshape([1, s, 1]) * (w * d.clone()).sum_dim(2) * inv_len.clone() * inv_len;
        let fs = d * (elastic + damping); // force on endpoint a, [B, S, 3]
        self.on_particles(fs, batch, p)
    }

    /// Each spring's force on its first end `fs` (`[B, S, 3]`), with its opposite on the second,
    /// summed on the particles (one scatter-add, Eq. 2) and, with particle masses, divided by
    /// each particle's relative mass: `[B, P, 3]`.
    fn on_particles(&self, fs: Tensor<3>, batch: usize, p: usize) -> Tensor<3> {
        let both = Tensor::cat(vec![fs.clone(), fs.neg()], 1); // [B, 2S, 3]
        let f = Tensor::zeros([batch, p, 3], &both.device()).select_assign(
            1,
            self.ends.clone(),
            both,
            burn::tensor::IndexingUpdateOp::Add,
        );
        match &self.force_scale {
            Some(scale) => f * scale.clone(),
            None => f,
        }
    }

    /// The forces of an isotropic viscosity on the springs as tensor ops, `[B, P, 3]`: spring
    /// `s = (a, b)` puts `β k_s (v_b − v_a)` on `a` and its opposite on `b` (the whole relative
    /// velocity, [`crate::sim::SimConfig::viscosity`]); with particle masses each particle's
    /// force is then divided by its relative mass, as the springs' are. The fused CPU step and
    /// rollout add the same term in their kernels; this is their reference, and what the
    /// tensor-op step (CubeCL devices, contact) adds to the spring forces.
    ///
    /// `v`: velocities `[B, P, 3]`; `k`: the springs' stiffness `[S]`; `viscosity`: `β`, s.
    pub fn viscous_forces(&self, v: Tensor<3>, k: Tensor<1>, viscosity: f64) -> Tensor<3> {
        let [batch, p, _] = v.dims();
        let s = self.num_springs;
        let w = v.clone().select(1, self.ib.clone()) - v.select(1, self.ia.clone());
        let fs = w * k.mul_scalar(viscosity).reshape([1, s, 1]); // on endpoint a, [B, S, 3]
        self.on_particles(fs, batch, p)
    }

    /// What softening the shear springs in compression changes in the spring forces, as tensor
    /// ops, `[B, P, 3]`: a shear spring `s = (a, b)` shorter than at rest pushes with
    /// `shear_compression · k_s` instead of `k_s` ([`crate::sim::SimConfig::shear_compression`]),
    /// so `(shear_compression − 1) k_s min(0, 1 − l0/|d|) d` is added on `a` and its opposite on
    /// `b`; with particle masses divided by each particle's relative mass, as the springs' forces
    /// are. The fused CPU step and rollout soften the springs in their kernels; this is their
    /// reference, and what the tensor-op step adds to the (linear) spring forces.
    ///
    /// `x`: positions `[B, P, 3]`; `k`: the springs' stiffness `[S]`.
    pub fn compression_forces(
        &self,
        x: Tensor<3>,
        k: Tensor<1>,
        shear_compression: f64,
    ) -> Tensor<3> {
        let [batch, p, _] = x.dims();
        let s = self.num_springs;
        let d = x.clone().select(1, self.ib.clone()) - x.select(1, self.ia.clone());
        let inv_len = (d.clone() * d.clone()).sum_dim(2).sqrt().recip(); // [B, S, 1]
        let l0 = self.rest_length.clone().reshape([1, s, 1]);
        let compressed = (l0 * inv_len).neg().add_scalar(1.0).clamp_max(0.0);
        let extra = (k * self.shear.clone()).mul_scalar(shear_compression - 1.0);
        let fs = d * (compressed * extra.reshape([1, s, 1])); // on endpoint a, [B, S, 3]
        self.on_particles(fs, batch, p)
    }
}

/// The curvature elements of a grid ([`Topology::curvature`], ours): three consecutive
/// particles `(i, j, l)` of a row, column or diagonal with the energy `½ κ_t |x_i − 2x_j + x_l|²`.
///
/// The force `κ_t e` with `e = x_i − 2x_j + x_l` acts as `−κ_t e` on `i` and `l` and `+2κ_t e`
/// on `j`: it sums to zero (momentum), vanishes on the flat rest grid and under rigid motions,
/// and is linear in the positions. The CPU kernels add it after the springs (their `k` holds
/// the springs' values, then `κ`: [`SpringNet::kernel_params`]); this tensor-op form is their
/// reference and runs where they do not.
#[derive(Module, Debug)]
pub struct Curvature {
    /// Stiffness `κ_t` in N/m, `[T]`.
    pub kappa: Param<Tensor<1>>,
    /// First particle `i` of every element, `[T]`.
    pub ii: Tensor<1, Int>,
    /// Middle particle `j`, `[T]`.
    pub ij: Tensor<1, Int>,
    /// Last particle `l`, `[T]`.
    pub il: Tensor<1, Int>,
    /// `[i, l, j]`, `[3T]`: the particle each entry of the forces goes to.
    pub ends: Tensor<1, Int>,
    /// The same entries grouped by particle: the forces are summed by
    /// [`kernels::segment`] (a gather on CubeCL devices, where a scatter walks every entry
    /// per column), as the GNN sums its messages.
    #[module(skip)]
    pub segments: Arc<Segments>,
}

impl Curvature {
    /// The elements `triples` over `particles` particles with stiffness `kappa` on `device`.
    pub fn new(triples: &[[usize; 3]], particles: usize, kappa: &[f64], device: &Device) -> Self {
        let t = triples.len();
        assert_eq!(kappa.len(), t, "one curvature stiffness per element");
        let int = |v: Vec<i64>| {
            let n = v.len();
            Tensor::<1, Int>::from_data(TensorData::new(v, [n]), device)
        };
        let col = |c: usize| -> Vec<i64> { triples.iter().map(|e| e[c] as i64).collect() };
        let ends = [col(0), col(2), col(1)].concat();
        let segments = Arc::new(Segments::new(&ends, particles));
        Self {
            kappa: Param::from_tensor(Tensor::<1>::from_data(
                TensorData::new(kappa.to_vec(), [t]),
                device,
            )),
            ii: int(col(0)),
            ij: int(col(1)),
            il: int(col(2)),
            ends: int(ends),
            segments,
        }
    }

    /// The elements' forces on every particle, `[B, P, 3]`.
    pub fn forces(&self, x: Tensor<3>) -> Tensor<3> {
        let [batch, p, _] = x.dims();
        let t = self.ii.dims()[0];
        let e = x.clone().select(1, self.ii.clone()) + x.clone().select(1, self.il.clone())
            - x.select(1, self.ij.clone()).mul_scalar(2.0); // [B, T, 3]
        let f = e * self.kappa.val().reshape([1, t, 1]);
        let all = Tensor::cat(vec![f.clone().neg(), f.clone().neg(), f.mul_scalar(2.0)], 1);
        // Entries as rows ([3T, B·3]), summed by particle, back to [B, P, 3].
        let rows = all.swap_dims(0, 1).reshape([3 * t, batch * 3]);
        let sum = DeviceSegments::over(self.segments.clone(), self.ends.clone()).sum(rows);
        sum.reshape([p, batch, 3]).swap_dims(0, 1)
    }

    /// Current stiffness values on the host.
    pub fn values(&self) -> Vec<f64> {
        to_f64(self.kappa.val())
    }
}

/// The learnable surrogate: one stiffness and one damping per spring, and with `cloth.curvature`
/// one stiffness per curvature element.
#[derive(Module, Debug)]
pub struct SpringNet {
    /// Stiffness `k_s` in N/m, `[S]`.
    pub k: Param<Tensor<1>>,
    /// Damping `b_s` in N·s/m, `[S]`.
    pub b: Param<Tensor<1>>,
    /// Endpoints and rest lengths (constants).
    pub graph: SpringGraph,
    /// The curvature elements, when the topology has them.
    pub curvature: Option<Curvature>,
}

impl SpringNet {
    /// A network over `topology` with the given per-spring `k` and `b` (and, when the topology
    /// has curvature elements, their stiffness `kappa` set by [`SpringNet::with_curvature`]; 0
    /// until then).
    pub fn new(topology: &Topology, k: &[f64], b: &[f64], device: &Device) -> Self {
        let s = topology.num_springs();
        assert_eq!(k.len(), s, "one stiffness per spring");
        assert_eq!(b.len(), s, "one damping per spring");
        // f64 host data, stored in the device's float dtype.
        let t = |v: &[f64]| {
            Param::from_tensor(Tensor::<1>::from_data(
                TensorData::new(v.to_vec(), [s]),
                device,
            ))
        };
        let curvature = (!topology.curvature.is_empty()).then(|| {
            Curvature::new(
                &topology.curvature,
                topology.num_particles(),
                &vec![0.0; topology.curvature.len()],
                device,
            )
        });
        Self {
            k: t(k),
            b: t(b),
            graph: SpringGraph::new(topology, device),
            curvature,
        }
    }

    /// The same network with curvature stiffness `kappa`, one value per element of the topology
    /// it was built on (a value for every element; none when it has none).
    ///
    /// Panics if the count differs.
    pub fn with_curvature(mut self, kappa: &[f64]) -> Self {
        match &mut self.curvature {
            Some(c) => {
                let t = c.ii.dims()[0];
                assert_eq!(kappa.len(), t, "one curvature stiffness per element");
                let device = c.ii.device();
                c.kappa = Param::from_tensor(Tensor::<1>::from_data(
                    TensorData::new(kappa.to_vec(), [t]),
                    &device,
                ));
            }
            None => assert!(kappa.is_empty(), "the topology has no curvature elements"),
        }
        self
    }

    /// Current curvature stiffness values on the host (empty without curvature elements).
    pub fn curvature_values(&self) -> Vec<f64> {
        self.curvature
            .as_ref()
            .map(Curvature::values)
            .unwrap_or_default()
    }

    /// The fused ops' `k` and `b`: the springs' values, then (with curvature elements) the
    /// elements' `κ` and, in `b`, zeros the kernels do not read (the elements have no damping;
    /// the entries keep `k` and `b` paired).
    pub fn kernel_params(&self) -> (Tensor<1>, Tensor<1>) {
        match &self.curvature {
            None => (self.k.val(), self.b.val()),
            Some(c) => {
                let kappa = c.kappa.val();
                let zeros = kappa.zeros_like();
                (
                    Tensor::cat(vec![self.k.val(), kappa], 0),
                    Tensor::cat(vec![self.b.val(), zeros], 0),
                )
            }
        }
    }

    /// The same network computing its forces with `kernel`.
    pub fn with_kernel(mut self, kernel: Kernel) -> Self {
        self.graph.kernel = kernel;
        self
    }

    /// A network with the same `k` and `b` on every spring.
    pub fn uniform(topology: &Topology, k: f64, b: f64, device: &Device) -> Self {
        let s = topology.num_springs();
        Self::new(topology, &vec![k; s], &vec![b; s], device)
    }

    /// Internal forces at state `(x, v)`, `[B, P, 3]`: the springs' (Eqs. 2, 4, see
    /// [`SpringGraph::spring_forces_reference`]) and the curvature elements'
    /// ([`Curvature::forces`]). This is the one place a rollout spends its time: it runs the
    /// fused kernel, or the tensor ops where `kernel` says so or the device has none.
    pub fn forces(&self, x: Tensor<3>, v: Tensor<3>) -> Tensor<3> {
        let graph = &self.graph;
        if graph.fused_curvature() {
            let (k, b) = self.kernel_params();
            return kernels::spring_forces(x, v, k, b, &graph.host);
        }
        let (k, b) = (self.k.val(), self.b.val());
        // The CubeCL kernels take the springs alone; the curvature elements' forces follow.
        let f = if graph.fused_forces() && graph.fused_on == FusedOn::Cube {
            kernels::spring_forces(x.clone(), v, k, b, &graph.host)
        } else {
            graph.spring_forces_reference(x.clone(), v, k, b)
        };
        match &self.curvature {
            Some(c) => f + c.forces(x),
            None => f,
        }
    }

    /// Current stiffness values on the host.
    pub fn k_values(&self) -> Vec<f64> {
        to_f64(self.k.val())
    }

    /// Current damping values on the host.
    pub fn b_values(&self) -> Vec<f64> {
        to_f64(self.b.val())
    }
}

/// Copies a float tensor to the host as `f64`.
pub fn to_f64<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    t.into_data()
        .try_into_vec_as::<f64>()
        .expect("float tensor data")
}
