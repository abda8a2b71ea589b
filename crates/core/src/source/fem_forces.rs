//! The FEM source's internal forces, eight triangles and eight hinges at a time.
//!
//! The element maths is [`fem`](super::fem)'s and [`triangles`]' own, evaluated over
//! [`Lanes`]: the mesh is laid out once in chunks of eight elements (the last padded with
//! copies of a real one whose results nobody reads), every chunk gathers its corners' positions
//! and velocities, computes its corner forces into a buffer, and each vertex then sums the
//! entries that belong to it. No element writes to a vertex, so there is nothing to race on or
//! to scatter, and a vertex sums its contributions in the order of the scalar loop (triangles in
//! mesh order, then hinges): the membrane forces are the scalar ones bit for bit, the bending
//! forces differ by the ≤ 2 ulp of the vectorised `atan2`.
//!
//! The chunk loop is compiled three times, for AVX-512, AVX2 and the baseline, and the CPU
//! picks at run time; all three perform the same IEEE operations (no fused multiply-adds), so
//! the results do not depend on the machine.

use std::cell::RefCell;

use super::fem::{Constants, Law, triangle_forces};
use crate::cloth::lanes::{LANES, Lanes, Real, each3, lanewise};
use crate::cloth::triangles::{Hinge, RestTriangle, V3, dihedral_of, scale};

/// Values per element corner in the output buffer: three coordinates of [`LANES`] lanes.
const CORNER: usize = 3 * LANES;

/// Eight triangles.
#[derive(Debug, Clone)]
struct TriangleChunk {
    vertices: [[u32; LANES]; 3],
    constants: Constants<Lanes>,
}

/// Eight hinges: corners `[a, b, c, d]` and the bending weight.
#[derive(Debug, Clone)]
struct HingeChunk {
    vertices: [[u32; LANES]; 4],
    weight: Lanes,
}

/// The mesh laid out for the chunked force loop.
#[derive(Debug, Clone)]
pub(super) struct ElementLanes {
    triangles: Vec<TriangleChunk>,
    hinges: Vec<HingeChunk>,
    /// Vertex `i`'s entries are `entries[first[i]..first[i + 1]]`: offsets into the output
    /// buffer of its corners' x values (y and z follow `LANES` and `2 · LANES` later).
    first: Vec<u32>,
    entries: Vec<u32>,
}

thread_local! {
    /// The corner forces of the last evaluation, one buffer per thread (generation steps one
    /// rollout per thread).
    static CORNERS: RefCell<Vec<f64>> = const { RefCell::new(Vec::new()) };
}

/// Lane `l` of chunk `chunk`, or element 0 for the padding past `count`.
fn padded(chunk: usize, l: usize, count: usize) -> usize {
    let e = chunk * LANES + l;
    if e < count { e } else { 0 }
}

impl ElementLanes {
    /// Lays out triangles with Lamé constants `(μ, λ)` and hinges `(hinge, weight)`.
    pub(super) fn new(
        vertices: usize,
        triangles: &[(RestTriangle, f64, f64)],
        hinges: &[(Hinge, f64)],
    ) -> Self {
        let tri_chunks = triangles.len().div_ceil(LANES);
        let hinge_chunks = hinges.len().div_ceil(LANES);
        let lanes = |f: &dyn Fn(usize) -> f64| Lanes(std::array::from_fn(f));
        let tris = (0..tri_chunks)
            .map(|c| {
                let at = |l: usize| &triangles[padded(c, l, triangles.len())];
                TriangleChunk {
                    vertices: std::array::from_fn(|k| std::array::from_fn(|l| at(l).0.v[k] as u32)),
                    constants: Constants {
                        mu: lanes(&|l| at(l).1),
                        lambda: lanes(&|l| at(l).2),
                        area: lanes(&|l| at(l).0.area),
                        dm_inv: std::array::from_fn(|i| {
                            std::array::from_fn(|j| lanes(&|l| at(l).0.dm_inv[i][j]))
                        }),
                    },
                }
            })
            .collect();
        let hinge_lanes = (0..hinge_chunks)
            .map(|c| {
                let at = |l: usize| &hinges[padded(c, l, hinges.len())];
                HingeChunk {
                    vertices: std::array::from_fn(|k| {
                        std::array::from_fn(|l| {
                            let h = at(l).0;
                            [h.a, h.b, h.c, h.d][k] as u32
                        })
                    }),
                    weight: lanes(&|l| at(l).1),
                }
            })
            .collect();
        // Every vertex's entries in the scalar loop's order: triangles (corners in order),
        // then hinges (corners c, d, a, b: the order of the dihedral's gradient).
        let mut lists: Vec<Vec<u32>> = vec![Vec::new(); vertices];
        let entry = |chunk: usize, corner: usize, lane: usize| {
            (chunk * CORNER * 3 + corner * CORNER + lane) as u32
        };
        for (e, (tri, _, _)) in triangles.iter().enumerate() {
            for (k, &i) in tri.v.iter().enumerate() {
                lists[i].push(entry(e / LANES, k, e % LANES));
            }
        }
        let base = tri_chunks * CORNER * 3;
        for (e, (h, _)) in hinges.iter().enumerate() {
            for (k, i) in [h.c, h.d, h.a, h.b].into_iter().enumerate() {
                lists[i].push((base + (e / LANES) * CORNER * 4 + k * CORNER + e % LANES) as u32);
            }
        }
        let mut first = Vec::with_capacity(vertices + 1);
        first.push(0);
        let mut entries = Vec::new();
        for list in lists {
            entries.extend(list);
            first.push(entries.len() as u32);
        }
        let lanes = Self {
            triangles: tris,
            hinges: hinge_lanes,
            first,
            entries,
        };
        let len = lanes.buffer_len();
        assert!(lanes.entries.iter().all(|&e| e as usize + 2 * LANES < len));
        lanes
    }

    /// Adds the membrane, strain-rate damping and bending forces at `(x, v)` to `out`.
    pub(super) fn add_forces(&self, law: Law, x: &[V3], v: &[V3], out: &mut [V3]) {
        assert!(x.len() == out.len() && v.len() == out.len() && out.len() + 1 == self.first.len());
        CORNERS.with_borrow_mut(|buf| {
            buf.resize(self.buffer_len(), 0.0);
            self.corner_forces(law, x, v, buf);
            for (i, o) in out.iter_mut().enumerate() {
                let mut acc = *o;
                for &e in &self.entries[self.first[i] as usize..self.first[i + 1] as usize] {
                    let e = e as usize;
                    // SAFETY: `new` checked that every entry's z value lies in the buffer,
                    // which was just sized to `buffer_len`.
                    unsafe {
                        acc[0] += *buf.get_unchecked(e);
                        acc[1] += *buf.get_unchecked(e + LANES);
                        acc[2] += *buf.get_unchecked(e + 2 * LANES);
                    }
                }
                *o = acc;
            }
        });
    }

    /// Values in the corner-force buffer.
    fn buffer_len(&self) -> usize {
        CORNER * (3 * self.triangles.len() + 4 * self.hinges.len())
    }

    /// Every element's corner forces into `buf`, with the widest SIMD the CPU has.
    fn corner_forces(&self, law: Law, x: &[V3], v: &[V3], buf: &mut [f64]) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F.
                return unsafe { self.corner_forces_avx512(law, x, v, buf) };
            }
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2.
                return unsafe { self.corner_forces_avx2(law, x, v, buf) };
            }
        }
        self.corner_forces_lanes(law, x, v, buf)
    }

    /// [`Self::corner_forces_lanes`] compiled with AVX-512.
    ///
    /// # Safety
    /// The CPU supports AVX-512F.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn corner_forces_avx512(&self, law: Law, x: &[V3], v: &[V3], buf: &mut [f64]) {
        self.corner_forces_lanes(law, x, v, buf)
    }

    /// [`Self::corner_forces_lanes`] compiled with AVX2.
    ///
    /// # Safety
    /// The CPU supports AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn corner_forces_avx2(&self, law: Law, x: &[V3], v: &[V3], buf: &mut [f64]) {
        self.corner_forces_lanes(law, x, v, buf)
    }

    #[inline(always)]
    fn corner_forces_lanes(&self, law: Law, x: &[V3], v: &[V3], buf: &mut [f64]) {
        let (tri_buf, hinge_buf) = buf.split_at_mut(self.triangles.len() * 3 * CORNER);
        for (chunk, dst) in self
            .triangles
            .iter()
            .zip(tri_buf.chunks_exact_mut(3 * CORNER))
        {
            let corners = &chunk.vertices;
            let velocities = if law.beta > 0.0 {
                Some(each3!(|k| gather(v, &corners[k])))
            } else {
                None
            };
            let f = triangle_forces(
                law,
                chunk.constants,
                each3!(|k| gather(x, &corners[k])),
                velocities,
            );
            store(&f, dst);
        }
        let minus_two = Lanes::splat(-2.0);
        for (chunk, dst) in self
            .hinges
            .iter()
            .zip(hinge_buf.chunks_exact_mut(4 * CORNER))
        {
            let corners = &chunk.vertices;
            let (theta, grads) = dihedral_of([
                gather(x, &corners[0]),
                gather(x, &corners[1]),
                gather(x, &corners[2]),
                gather(x, &corners[3]),
            ]);
            let coef = minus_two * chunk.weight * theta;
            for (k, g) in grads.into_iter().enumerate() {
                store(&[scale(g, coef)], &mut dst[k * CORNER..(k + 1) * CORNER]);
            }
        }
    }
}

/// The points `y[idx[l]]` as lanes.
#[inline(always)]
fn gather(y: &[V3], idx: &[u32; LANES]) -> [Lanes; 3] {
    each3!(|c| Lanes(lanewise!(|l| y[idx[l] as usize][c])))
}

/// Writes corner forces as `[corner][coordinate][lane]`.
#[inline(always)]
fn store(forces: &[[Lanes; 3]], dst: &mut [f64]) {
    for (corner, f) in forces.iter().enumerate() {
        for (c, lanes) in f.iter().enumerate() {
            let at = corner * CORNER + c * LANES;
            dst[at..at + LANES].copy_from_slice(&lanes.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::fem::Membrane;

    #[test]
    fn every_instruction_set_gives_the_same_bits() {
        // A 5 × 3 strip of two triangles per cell with a hinge on every interior edge.
        let nx = 5;
        let uv: Vec<[f64; 2]> = (0..15)
            .map(|i| [(i % nx) as f64, (i / nx) as f64])
            .collect();
        let mut tris = Vec::new();
        for r in 0..2 {
            for c in 0..nx - 1 {
                let p = r * nx + c;
                tris.push([p, p + 1, p + nx + 1]);
                tris.push([p, p + nx + 1, p + nx]);
            }
        }
        let triangles: Vec<(RestTriangle, f64, f64)> = tris
            .iter()
            .enumerate()
            .map(|(e, &t)| (RestTriangle::new(&uv, t).unwrap(), 1.0 + e as f64, 0.5))
            .collect();
        let hinges: Vec<(Hinge, f64)> = crate::cloth::triangles::hinges(&tris)
            .into_iter()
            .enumerate()
            .map(|(e, h)| (h, 0.1 * (1 + e) as f64))
            .collect();
        let lanes = ElementLanes::new(uv.len(), &triangles, &hinges);
        let x: Vec<V3> = uv
            .iter()
            .enumerate()
            .map(|(i, p)| [p[0] * 1.1, p[1] * 0.9, 0.3 * (i as f64 * 1.7).sin()])
            .collect();
        let v: Vec<V3> = (0..uv.len())
            .map(|i| [(i as f64).cos(), 0.5, (i as f64 * 0.3).sin()])
            .collect();
        let law = Law {
            membrane: Membrane::Corotational,
            beta: 0.01,
        };
        let size = lanes.buffer_len();
        let (mut dispatched, mut baseline) = (vec![0.0; size], vec![0.0; size]);
        lanes.corner_forces(law, &x, &v, &mut dispatched);
        lanes.corner_forces_lanes(law, &x, &v, &mut baseline);
        assert!(baseline.iter().any(|f| f.abs() > 0.1));
        assert_eq!(
            dispatched.iter().map(|f| f.to_bits()).collect::<Vec<_>>(),
            baseline.iter().map(|f| f.to_bits()).collect::<Vec<_>>()
        );
    }
}
