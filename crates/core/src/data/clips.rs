//! Clip datasets (paper App. A): rollouts resampled to the surrogate's particles and cut into
//! non-overlapping clips of `T` steps; a random fraction of them is kept, and the clips of the
//! last second of every rollout form the low-velocity set of the stiffness pass.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::{Result, bail};
use burn::tensor::{Device, Tensor, TensorData};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng, rngs::StdRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::rollout::{MeshTruth, Rollout};
use crate::cloth::{Resampler, Topology};
use crate::settings::Auto;

/// How rollouts are cut into clips: part of the `[data]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClipConfig {
    /// Steps per clip `T` in data frames (the paper uses 500 at 1 ms); `"auto"`: half a second
    /// of frames ([`ClipConfig::steps_for`]).
    pub steps: Auto<usize>,
    /// Fraction of a rollout's regular clips that are kept (the paper keeps 6 %).
    pub fraction: f64,
    /// The low-velocity set: clips within this many seconds of a rollout's end.
    pub low_velocity_seconds: f64,
    /// Fraction of the low-velocity clips that are kept (the paper keeps 50 %).
    pub low_velocity_fraction: f64,
    /// Seed of the selection.
    pub seed: u64,
}

impl Default for ClipConfig {
    fn default() -> Self {
        Self {
            steps: Auto::Auto,
            fraction: 1.0,
            low_velocity_seconds: 1.0,
            low_velocity_fraction: 1.0,
            seed: 0,
        }
    }
}

/// A clip chosen by [`ClipConfig::plan`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlannedClip {
    /// First frame on the rollout's timeline.
    pub start: usize,
    /// In the low-velocity set (else a regular clip).
    pub low_velocity: bool,
}

/// The span of a clip when `data.clips.steps = "auto"`: the paper's 500 steps of 1 ms.
pub const AUTO_CLIP_SECONDS: f64 = 0.5;

impl ClipConfig {
    /// Steps per clip for frames `frame_dt` apart: the configured number, or
    /// [`AUTO_CLIP_SECONDS`] worth of frames (at least 2).
    pub fn steps_for(&self, frame_dt: f64) -> usize {
        self.steps
            .value()
            .unwrap_or_else(|| ((AUTO_CLIP_SECONDS / frame_dt).round() as usize).max(2))
    }

    /// The clips kept from a rollout called `name` whose timeline has `frames` frames, the first
    /// usable one (with a known velocity) being `first`.
    ///
    /// Regular clips start at `first, first + T, …`; low-velocity clips end at the last frame
    /// and go back in steps of `T` while they stay within the last `low_velocity_seconds`.
    /// The choice is a deterministic function of the seed and the rollout's name, so the
    /// generator can store exactly the windows that training will later cut.
    pub fn plan(&self, name: &str, frames: usize, frame_dt: f64, first: usize) -> Vec<PlannedClip> {
        let t = self.steps_for(frame_dt);
        let mut rng = StdRng::seed_from_u64(self.seed ^ fnv1a(name));
        let mut out = Vec::new();
        let mut start = first;
        while start + t < frames {
            if rng.random::<f64>() < self.fraction {
                out.push(PlannedClip {
                    start,
                    low_velocity: false,
                });
            }
            start += t;
        }
        let last = frames.saturating_sub(1);
        let window = (self.low_velocity_seconds / frame_dt).round() as usize;
        let lowest = first.max(last.saturating_sub(window));
        let mut end = last;
        while end >= lowest + t && self.low_velocity_seconds > 0.0 {
            if rng.random::<f64>() < self.low_velocity_fraction {
                out.push(PlannedClip {
                    start: end - t,
                    low_velocity: true,
                });
            }
            end -= t;
        }
        out
    }
}

/// 64-bit FNV-1a of a string: a stable per-rollout seed.
pub(crate) fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

/// A rollout resampled to the surrogate's particles: positions and velocities per stored frame.
#[derive(Debug, Clone)]
pub struct Track {
    /// Stored frames.
    pub frames: usize,
    /// Particles.
    pub particles: usize,
    /// Positions `[F, P, 3]`.
    pub positions: Vec<f32>,
    /// Velocities `[F, P, 3]` (stored, or central differences of positions — backward at a
    /// window's last frame; frame 0 of a window without stored velocities starts no clip).
    pub velocities: Vec<f32>,
    /// Whether the velocities are the file's own (not differences of positions).
    pub stored_velocities: bool,
    /// Pinned particles.
    pub pinned: Vec<bool>,
    /// Whether each particle was seen in each frame, `[F, P]` (a particle resampled from
    /// landmarks is seen where all of them are); `None`: every particle in every frame.
    pub visible: Option<Vec<bool>>,
}

impl Track {
    /// A one-frame track of particles at rest at `x0`, none pinned (a cloth released in a
    /// scene).
    pub fn at_rest(x0: &[[f64; 3]]) -> Self {
        let p = x0.len();
        Self {
            frames: 1,
            particles: p,
            positions: x0.iter().flat_map(|q| q.map(|c| c as f32)).collect(),
            velocities: vec![0.0; p * 3],
            stored_velocities: true,
            pinned: vec![false; p],
            visible: None,
        }
    }

    /// Resamples `rollout` to the particles of `resampler`.
    pub fn new(rollout: &Rollout, resampler: &Resampler) -> Self {
        if resampler.is_identity(rollout.landmarks) && rollout.velocities.is_some() {
            return Self::from_rollout(rollout.clone(), resampler);
        }
        Self::resampled(rollout, resampler)
    }

    /// [`Track::new`] taking the rollout by value: when the particles are the landmarks and the
    /// velocities are stored, the arrays are moved, not copied.
    pub fn from_rollout(rollout: Rollout, resampler: &Resampler) -> Self {
        if !resampler.is_identity(rollout.landmarks) || rollout.velocities.is_none() {
            return Self::resampled(&rollout, resampler);
        }
        Self {
            frames: rollout.frames,
            particles: rollout.landmarks,
            pinned: resampler.pinned(&rollout.pinned),
            velocities: rollout.velocities.expect("checked above"),
            stored_velocities: true,
            positions: rollout.positions,
            visible: rollout.visible,
        }
    }

    fn resampled(rollout: &Rollout, resampler: &Resampler) -> Self {
        let (f, n, p) = (rollout.frames, rollout.landmarks, resampler.num_particles());
        let mut positions = vec![0f32; f * p * 3];
        let mut velocities = vec![0f32; f * p * 3];
        let mut buf = vec![0f64; p * 3];
        for frame in 0..f {
            resampler.apply3(
                &rollout.positions[frame * n * 3..(frame + 1) * n * 3],
                &mut buf,
            );
            for (dst, &v) in positions[frame * p * 3..(frame + 1) * p * 3]
                .iter_mut()
                .zip(&buf)
            {
                *dst = v as f32;
            }
        }
        match &rollout.velocities {
            Some(vel) => {
                for frame in 0..f {
                    resampler.apply3(&vel[frame * n * 3..(frame + 1) * n * 3], &mut buf);
                    for (dst, &v) in velocities[frame * p * 3..(frame + 1) * p * 3]
                        .iter_mut()
                        .zip(&buf)
                    {
                        *dst = v as f32;
                    }
                }
            }
            None => {
                // Central differences inside each stored window (second-order: at camera rate a
                // backward difference lags by half a frame, ≈ g·Δt/2 under gravity alone), a
                // backward difference at its last frame; its first frame has no velocity and
                // starts no clip.
                let inv = 1.0 / rollout.frame_dt;
                let at = |frame: usize, i: usize| positions[frame * p * 3 + i] as f64;
                for seg in &rollout.segments {
                    let last = seg.offset + seg.len - 1;
                    for frame in seg.offset + 1..=last {
                        for i in 0..p * 3 {
                            let v = if frame < last {
                                (at(frame + 1, i) - at(frame - 1, i)) * 0.5 * inv
                            } else {
                                (at(frame, i) - at(frame - 1, i)) * inv
                            };
                            velocities[frame * p * 3 + i] = v as f32;
                        }
                    }
                }
            }
        }
        Self {
            frames: f,
            particles: p,
            positions,
            velocities,
            stored_velocities: rollout.velocities.is_some(),
            pinned: resampler.pinned(&rollout.pinned),
            visible: rollout.visible.as_ref().map(|seen| {
                seen.chunks_exact(n)
                    .flat_map(|frame| resampler.visible(frame))
                    .collect()
            }),
        }
    }

    /// Whether particle `i` was seen in frame `f`.
    pub fn seen(&self, f: usize, i: usize) -> bool {
        self.visible
            .as_ref()
            .is_none_or(|v| v[f * self.particles + i])
    }

    /// Whether particle `i` is seen in every frame of `frames` that the track holds.
    pub fn seen_throughout(&self, i: usize, frames: std::ops::RangeInclusive<usize>) -> bool {
        self.visible.is_none()
            || frames
                .take_while(|&f| f < self.frames)
                .all(|f| self.seen(f, i))
    }

    /// Where each sample `[F × P]` is seen or its landmark's hidden run is bridgeable: at most
    /// `max_gap` frames long, with seen frames on both sides (the reader's fill there rests on
    /// seen frames close by). `None` where every landmark is seen in every frame.
    pub fn bridged(&self, max_gap: usize) -> Option<Vec<bool>> {
        let seen = self.visible.as_ref()?;
        let (f, p) = (self.frames, self.particles);
        let mut out = seen.clone();
        for i in 0..p {
            let mut start = None; // first hidden frame of the current run
            for frame in 0..f {
                match (seen[frame * p + i], start) {
                    (false, None) => start = Some(frame),
                    (true, Some(a)) => {
                        if a > 0 && frame - a <= max_gap {
                            (a..frame).for_each(|q| out[q * p + i] = true);
                        }
                        start = None;
                    }
                    _ => {}
                }
            }
        }
        Some(out)
    }

    /// Whether particle `i`'s velocity at frame `f` rests on seen positions: stored velocities
    /// on frame `f` alone, differences of positions on frames `f − 1 … f + 1`.
    pub fn velocity_seen(&self, i: usize, f: usize) -> bool {
        if self.stored_velocities {
            self.seen_throughout(i, f..=f)
        } else {
            self.seen_throughout(i, f.saturating_sub(1)..=f + 1)
        }
    }

    fn bytes(&self) -> usize {
        (self.positions.len() + self.velocities.len()) * 4
    }
}

/// One clip: a window of `T + 1` stored frames of one rollout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClipRef {
    /// Index of the rollout in the set.
    pub rollout: usize,
    /// First stored frame.
    pub offset: usize,
    /// Its frame on the rollout's timeline.
    pub start: usize,
}

/// A batch of clips as tensors.
#[derive(Debug, Clone)]
pub struct ClipBatch {
    /// Target positions `[B, T + 1, P, 3]`.
    pub positions: Tensor<4>,
    /// Target velocities `[B, T + 1, P, 3]`.
    pub velocities: Tensor<4>,
    /// Target net forces per frame interval, `M (v̂_{j+1} − v̂_j) / Δt` (the corrected Eq. 8),
    /// `[B, T, P, 3]`, computed in f64 on the host.
    pub forces: Tensor<4>,
    /// 1 for pinned particles, `[B, P, 1]`.
    pub pinned: Tensor<3>,
    /// Where the clips' particles were seen, when some were not (tracked markers); `None`:
    /// every particle in every frame.
    pub seen: Option<SeenMask>,
}

/// The shared metadata of a set of rollouts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SetInfo {
    /// Time between frames, s.
    pub frame_dt: f64,
    /// Cloth mass, kg.
    pub total_mass: f64,
    /// Rest rectangle width, m.
    pub width: f64,
    /// Rest rectangle height, m.
    pub height: f64,
    /// Number of landmarks.
    pub landmarks: usize,
    /// Gravity the files state (key `gravity`).
    pub gravity: Option<[f64; 3]>,
    /// Rayleigh damping per landmark the files state, N·s/m (key `rayleigh`).
    pub rayleigh: Option<f64>,
    /// The positions' measurement noise the files state, m per axis (key `position_noise`).
    pub position_noise: Option<f64>,
}

impl SetInfo {
    /// The files' Rayleigh damping for particles of `particle_mass`: the same damping rate per
    /// unit mass as the landmarks, which share `total_mass` equally.
    pub(crate) fn rayleigh_for(&self, particle_mass: f64) -> Option<f64> {
        self.rayleigh
            .map(|c| c * self.landmarks as f64 / self.total_mass * particle_mass)
    }
}

struct Entry {
    path: PathBuf,
    name: String,
}

/// Rollout files cut into clips, loaded on demand with a bounded cache.
///
/// `Sync`: batches may be assembled on another thread while the current one trains
/// ([`ClipSet::host_batch`]).
pub struct ClipSet {
    entries: Vec<Entry>,
    /// Shared frame step, mass and size of every rollout.
    pub info: SetInfo,
    /// The surrogate's grid.
    pub topology: Topology,
    /// Regular clips (the damping pass and single-pass training).
    pub regular: Vec<ClipRef>,
    /// Low-velocity clips (the stiffness pass).
    pub low_velocity: Vec<ClipRef>,
    /// Steps per clip.
    pub steps: usize,
    resampler: Option<Resampler>,
    cache: Mutex<Cache>,
}

/// Resampled rollouts kept in memory, oldest evicted first.
struct Cache {
    tracks: HashMap<usize, Arc<Track>>,
    order: VecDeque<usize>,
    bytes: usize,
    limit: usize,
}

impl Cache {
    /// Keeps `track` if it fits after evicting older entries (never more than `limit` bytes).
    fn insert(&mut self, i: usize, track: &Arc<Track>) {
        if track.bytes() > self.limit || self.tracks.contains_key(&i) {
            return;
        }
        while self.bytes + track.bytes() > self.limit {
            let Some(old) = self.order.pop_front() else {
                break;
            };
            if let Some(t) = self.tracks.remove(&old) {
                self.bytes -= t.bytes();
            }
        }
        self.bytes += track.bytes();
        self.tracks.insert(i, track.clone());
        self.order.push_back(i);
    }
}

impl ClipSet {
    /// Indexes `paths`: reads every file once to validate it and plan its clips.
    ///
    /// `topology` makes the surrogate topology from the first rollout (its rest rectangle, or
    /// its mesh).
    pub fn open(
        paths: &[PathBuf],
        clips: &ClipConfig,
        topology_of: impl Fn(&Rollout) -> Result<Topology>,
        cache_bytes: usize,
        mut progress: impl FnMut(usize),
    ) -> Result<Self> {
        if paths.is_empty() {
            bail!("no rollout files to cut into clips");
        }
        let mut entries = Vec::new();
        let (mut regular, mut low_velocity) = (Vec::new(), Vec::new());
        let mut info: Option<SetInfo> = None;
        let mut topology = None;
        let mut resampler: Option<Resampler> = None;
        let mut shape: Option<SetShape> = None;
        let mut cache = Cache {
            tracks: HashMap::new(),
            order: VecDeque::new(),
            bytes: 0,
            limit: cache_bytes,
        };
        for (i, path) in paths.iter().enumerate() {
            let rollout = Rollout::load(path)?;
            let this = SetInfo::of(&rollout);
            match info {
                None => {
                    let topo = topology_of(&rollout)?;
                    resampler = Some(Resampler::new(&rollout.rest_uv, &topo.rest_uv));
                    topology = Some(topo);
                    info = Some(this);
                }
                Some(first) => check_same(&first, &this, path, &paths[0])?,
            }
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let (plain, slow) = clip_refs(clips, &rollout, i, &name);
            regular.extend(plain);
            low_velocity.extend(slow);
            let resampler_ref = resampler.as_ref().expect("set on the first file");
            SetShape::check(&mut shape, &rollout, path, &paths[0])?;
            if cache.bytes < cache.limit {
                cache.insert(i, &Arc::new(Track::from_rollout(rollout, resampler_ref)));
            }
            entries.push(Entry {
                path: path.clone(),
                name,
            });
            progress(i + 1);
        }
        if regular.is_empty() && low_velocity.is_empty() {
            bail!(
                "the rollouts yield no clip of {} steps (they are too short, or `data.fraction` / \
                 `data.low_velocity_fraction` kept none)",
                clips.steps_for(info.map_or(1.0, |i| i.frame_dt))
            );
        }
        Ok(Self {
            entries,
            info: info.expect("at least one file"),
            topology: topology.expect("at least one file"),
            regular,
            low_velocity,
            steps: clips.steps_for(info.expect("at least one file").frame_dt),
            resampler,
            cache: Mutex::new(cache),
        })
    }

    /// Number of rollouts.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the set holds no rollout.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// File name of rollout `i`.
    pub fn name(&self, i: usize) -> &str {
        &self.entries[i].name
    }

    /// Every clip: the regular ones, then the low-velocity ones.
    pub fn all_clips(&self) -> Vec<ClipRef> {
        self.regular
            .iter()
            .chain(&self.low_velocity)
            .copied()
            .collect()
    }

    /// Whether every particle sits on one landmark (no interpolation between the data's
    /// vertices; [`Resampler::is_exact`]).
    pub(crate) fn particles_are_landmarks(&self) -> bool {
        self.resampler.as_ref().is_some_and(Resampler::is_exact)
    }

    /// Particle mass `ρA/P`.
    pub fn particle_mass(&self) -> f64 {
        self.info.total_mass / self.topology.num_particles() as f64
    }

    /// The resampled rollout `i` (from the cache or from disk).
    pub fn track(&self, i: usize) -> Result<Arc<Track>> {
        if let Some(t) = self.cache.lock().expect("cache lock").tracks.get(&i) {
            return Ok(t.clone());
        }
        let rollout = Rollout::load(&self.entries[i].path)?;
        let track = Arc::new(Track::from_rollout(
            rollout,
            self.resampler.as_ref().expect("set"),
        ));
        self.cache.lock().expect("cache lock").insert(i, &track);
        Ok(track)
    }

    /// Assembles clips on the host (reading the rollouts that are not cached in parallel).
    pub fn host_batch(&self, clips: &[ClipRef]) -> Result<HostBatch> {
        self.host_batch_of(clips, self.steps)
    }

    /// [`host_batch`](Self::host_batch) of the first `steps` steps of each clip (a model that
    /// reads a window of each clip moves the [`ClipRef`]s and uploads only the window).
    ///
    /// Panics if `steps` is 0 or more than the clips'.
    pub(crate) fn host_batch_of(&self, clips: &[ClipRef], steps: usize) -> Result<HostBatch> {
        assert!(
            (1..=self.steps).contains(&steps),
            "{steps} steps of clips of {}",
            self.steps
        );
        // Each rollout once, however many of the batch's clips it holds.
        let mut ids: Vec<usize> = clips.iter().map(|c| c.rollout).collect();
        ids.sort_unstable();
        ids.dedup();
        let loaded: HashMap<usize, Arc<Track>> = ids
            .par_iter()
            .map(|&i| Ok((i, self.track(i)?)))
            .collect::<Result<_>>()?;
        let tracks: Vec<(Arc<Track>, usize)> = clips
            .iter()
            .map(|c| (loaded[&c.rollout].clone(), c.offset))
            .collect();
        let views: Vec<(&Track, usize)> = tracks.iter().map(|(t, o)| (t.as_ref(), *o)).collect();
        Ok(HostBatch::new(
            &views,
            steps,
            self.particle_mass(),
            self.info.frame_dt,
        ))
    }

    /// Assembles clips into tensors on `device`.
    pub fn batch(&self, clips: &[ClipRef], device: &Device) -> Result<ClipBatch> {
        self.host_batch(clips)?.to_device(device)
    }
}

/// Which targets of a [`ClipBatch`] rest on seen particles: 1 where they do, 0 where not.
#[derive(Debug, Clone)]
pub struct SeenMask {
    /// Positions seen, `[B, T + 1, P, 1]`.
    pub positions: Tensor<4>,
    /// Target forces whose two velocities rest on seen positions
    /// ([`Track::velocity_seen`]), `[B, T, P, 1]`.
    pub forces: Tensor<4>,
}

/// A batch of clips on the host, before it becomes a [`ClipBatch`] on a device.
#[derive(Debug, Clone)]
pub struct HostBatch {
    positions: Vec<f32>,
    velocities: Vec<f32>,
    forces: Vec<f32>,
    pinned: Vec<f32>,
    /// `[B, T + 1, P]` and `[B, T, P]` masks of seen positions and forces, when some clip's
    /// track has hidden particles.
    seen: Option<(Vec<f32>, Vec<f32>)>,
    clips: usize,
    steps: usize,
    particles: usize,
}

impl HostBatch {
    /// Stacks `steps`-step windows `(track, first stored frame)`; target forces are
    /// `mass (v̂_{j+1} − v̂_j) / frame_dt`, computed in f64.
    pub fn new(clips: &[(&Track, usize)], steps: usize, mass: f64, frame_dt: f64) -> Self {
        let (t, b) = (steps, clips.len());
        assert!(t >= 1, "a clip needs at least one step");
        let p = clips.first().map_or(0, |c| c.0.particles);
        let frame = p * 3;
        let (states, forces) = ((t + 1) * frame, t * frame);
        for (track, _) in clips {
            assert_eq!(
                track.particles, p,
                "clips of one batch share the particle count"
            );
        }
        // One clip per task: each writes its own rows (a batch is hundreds of MB to copy).
        let mut pos = vec![0f32; b * states];
        let mut vel = vec![0f32; b * states];
        let mut force = vec![0f32; b * forces];
        let m_over_dt = mass / frame_dt;
        pos.par_chunks_mut(states.max(1))
            .zip(vel.par_chunks_mut(states.max(1)))
            .zip(force.par_chunks_mut(forces.max(1)))
            .zip(clips.par_iter())
            .for_each(|(((pos, vel), force), &(track, offset))| {
                let range = offset * frame..(offset + t + 1) * frame;
                pos.copy_from_slice(&track.positions[range.clone()]);
                let v = &track.velocities[range];
                vel.copy_from_slice(v);
                for ((f, &next), &here) in force.iter_mut().zip(&v[frame..]).zip(&v[..t * frame]) {
                    *f = (m_over_dt * (next as f64 - here as f64)) as f32;
                }
            });
        let pinned = clips
            .iter()
            .flat_map(|(track, _)| track.pinned.iter().map(|&x| x as u8 as f32))
            .collect();
        let seen = clips
            .iter()
            .any(|(track, _)| track.visible.is_some())
            .then(|| {
                let mut x = Vec::with_capacity(b * (t + 1) * p);
                let mut f = Vec::with_capacity(b * t * p);
                for &(track, offset) in clips {
                    for j in offset..=offset + t {
                        x.extend((0..p).map(|i| track.seen(j, i) as u8 as f32));
                    }
                    for j in offset..offset + t {
                        f.extend((0..p).map(|i| {
                            (track.velocity_seen(i, j) && track.velocity_seen(i, j + 1)) as u8
                                as f32
                        }));
                    }
                }
                (x, f)
            });
        Self {
            positions: pos,
            velocities: vel,
            forces: force,
            pinned,
            seen,
            clips: b,
            steps: t,
            particles: p,
        }
    }

    /// Refuses a batch whose largest tensor (positions or velocities, `[B, T + 1, P, 3]` f32)
    /// is over `device`'s largest buffer, naming the sizes and what to lower.
    fn check_fits(&self, device: &Device) -> Result<()> {
        let bytes = (self.positions.len() * std::mem::size_of::<f32>()) as u64;
        match crate::backend::max_buffer_bytes(device) {
            Some(max) if bytes > max => anyhow::bail!(
                "a batch of {} clips of {} steps over {} particles needs {:.2} GB per tensor, \
                 over this device's largest buffer ({:.2} GB): lower the clips per batch \
                 (`train.*.batch`) or the steps per clip (`data.clips.steps`)",
                self.clips,
                self.steps,
                self.particles,
                bytes as f64 / 1e9,
                max as f64 / 1e9
            ),
            _ => Ok(()),
        }
    }

    /// Uploads the batch to `device`, refusing one that does not fit its buffers.
    pub fn to_device(self, device: &Device) -> Result<ClipBatch> {
        self.check_fits(device)?;
        let (b, t, p) = (self.clips, self.steps, self.particles);
        let t4 = |v: Vec<f32>, n: usize| {
            Tensor::<4>::from_data(TensorData::new(v, [b, n, p, 3]), device)
        };
        Ok(ClipBatch {
            positions: t4(self.positions, t + 1),
            velocities: t4(self.velocities, t + 1),
            forces: t4(self.forces, t),
            pinned: Tensor::from_data(TensorData::new(self.pinned, [b, p, 1]), device),
            seen: self.seen.map(|(x, f)| SeenMask {
                positions: Tensor::from_data(TensorData::new(x, [b, t + 1, p, 1]), device),
                forces: Tensor::from_data(TensorData::new(f, [b, t, p, 1]), device),
            }),
        })
    }
}

impl ClipBatch {
    /// Stacks `steps`-step windows `(track, first stored frame)` into a batch on `device` (see
    /// [`HostBatch::new`] and [`HostBatch::to_device`]).
    pub fn new(
        clips: &[(&Track, usize)],
        steps: usize,
        mass: f64,
        frame_dt: f64,
        device: &Device,
    ) -> Result<Self> {
        HostBatch::new(clips, steps, mass, frame_dt).to_device(device)
    }
}

/// Epoch-style sampler: a shuffled pass over a pool, reshuffled when exhausted.
#[derive(Debug, Clone)]
pub struct Sampler {
    order: Vec<usize>,
    at: usize,
    rng: StdRng,
}

impl Sampler {
    /// A sampler over `n` items.
    pub fn new(n: usize, seed: u64) -> Self {
        Self {
            order: (0..n).collect(),
            at: n,
            rng: StdRng::seed_from_u64(seed),
        }
    }

    /// The next `k` items (distinct when `k ≤ n`).
    pub fn next(&mut self, k: usize) -> Vec<usize> {
        let mut out = Vec::with_capacity(k);
        while out.len() < k && !self.order.is_empty() {
            if self.at == self.order.len() {
                self.order.shuffle(&mut self.rng);
                self.at = 0;
            }
            out.push(self.order[self.at]);
            self.at += 1;
        }
        out
    }
}

impl SetInfo {
    /// The constants of `rollout`.
    pub fn of(rollout: &Rollout) -> Self {
        Self {
            frame_dt: rollout.frame_dt,
            total_mass: rollout.total_mass,
            width: rollout.width,
            height: rollout.height,
            landmarks: rollout.landmarks,
            gravity: rollout.gravity,
            rayleigh: rollout.rayleigh,
            position_noise: rollout.position_noise,
        }
    }
}

impl SetShape {
    /// Takes the first rollout's shape into `shape`, or refuses one of the set whose landmarks
    /// or mesh differ from it (`first` is the first rollout's file).
    fn check(shape: &mut Option<Self>, rollout: &Rollout, path: &Path, first: &Path) -> Result<()> {
        if let Some(set) = shape {
            check_same_landmarks(&set.rest_uv, &rollout.rest_uv, path, first)?;
            check_same_mesh(set.triangles.as_ref(), rollout.mesh.as_ref(), path, first)?;
        }
        shape.get_or_insert_with(|| Self {
            rest_uv: rollout.rest_uv.clone(),
            triangles: rollout.mesh.as_ref().map(|m| m.triangles.clone()),
        });
        Ok(())
    }
}

/// The clips of rollout `i` (file name `name`) that the clip plan keeps and its stored frames
/// hold: the regular ones and the low-velocity ones.
fn clip_refs(
    clips: &ClipConfig,
    rollout: &Rollout,
    i: usize,
    name: &str,
) -> (Vec<ClipRef>, Vec<ClipRef>) {
    let (mut regular, mut low_velocity) = (Vec::new(), Vec::new());
    let first = rollout.first_usable_frame();
    let plan = clips.plan(name, rollout.timeline_frames(), rollout.frame_dt, first);
    for c in plan {
        let steps = clips.steps_for(rollout.frame_dt);
        let Some(offset) = stored_offset(rollout, c.start, steps, first) else {
            continue;
        };
        let r = ClipRef {
            rollout: i,
            offset,
            start: c.start,
        };
        if c.low_velocity {
            low_velocity.push(r);
        } else {
            regular.push(r);
        }
    }
    (regular, low_velocity)
}

/// Stored index of timeline frame `start` if frames `start..=start + steps` lie in one stored
/// window and `start` has a known velocity.
fn stored_offset(rollout: &Rollout, start: usize, steps: usize, first: usize) -> Option<usize> {
    rollout.segments.iter().find_map(|s| {
        let usable = s.start + first;
        (start >= usable && start + steps < s.start + s.len).then(|| s.offset + start - s.start)
    })
}

/// What every rollout of a set shares with the first: landmarks and mesh.
struct SetShape {
    rest_uv: Vec<[f64; 2]>,
    triangles: Option<Vec<[usize; 3]>>,
}

/// Errors unless `b` (of `path`) has the landmarks `a` of the set's first file `first`.
pub fn check_same_landmarks(
    a: &[[f64; 2]],
    b: &[[f64; 2]],
    path: &Path,
    first: &Path,
) -> Result<()> {
    if a.len() != b.len() || a.iter().zip(b).any(|(x, y)| x != y) {
        bail!(
            "{}: key `rest_uv` differs from {}: all rollouts of a set must share their landmarks",
            path.display(),
            first.display()
        );
    }
    Ok(())
}

/// Errors unless `b` (of `path`) has the `triangles` `a` of the set's first file `first`, or
/// both have none.
pub fn check_same_mesh(
    a: Option<&Vec<[usize; 3]>>,
    b: Option<&MeshTruth>,
    path: &Path,
    first: &Path,
) -> Result<()> {
    if b.map(|m| &m.triangles) != a {
        bail!(
            "{}: key `triangles` differs from {}: all rollouts of a set must share their mesh \
             (or all have none)",
            path.display(),
            first.display()
        );
    }
    Ok(())
}

/// Errors unless `b` (of `path`) has the frame step, mass and rectangle `a` of the set's first
/// file `first`; the error names the key.
pub fn check_same(a: &SetInfo, b: &SetInfo, path: &Path, first: &Path) -> Result<()> {
    let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * x.abs().max(y.abs());
    for (key, x, y) in [
        ("frame_dt", a.frame_dt, b.frame_dt),
        ("total_mass", a.total_mass, b.total_mass),
        ("width", a.width, b.width),
        ("height", a.height, b.height),
    ] {
        if !close(x, y) {
            bail!(
                "{}: key `{key}` = {y} differs from {} ({x}): all rollouts of a set must share \
                 the frame step, mass and rest rectangle",
                path.display(),
                first.display()
            );
        }
    }
    let same = |x: Option<&[f64]>, y: Option<&[f64]>| match (x, y) {
        (None, None) => true,
        (Some(x), Some(y)) => x.iter().zip(y).all(|(&x, &y)| close(x, y)),
        _ => false,
    };
    for (key, x, y) in [
        (
            "gravity",
            a.gravity.as_ref().map(|g| &g[..]),
            b.gravity.as_ref().map(|g| &g[..]),
        ),
        (
            "rayleigh",
            a.rayleigh.as_ref().map(std::slice::from_ref),
            b.rayleigh.as_ref().map(std::slice::from_ref),
        ),
        (
            "position_noise",
            a.position_noise.as_ref().map(std::slice::from_ref),
            b.position_noise.as_ref().map(std::slice::from_ref),
        ),
    ] {
        if !same(x, y) {
            bail!(
                "{}: key `{key}` = {y:?} differs from {} ({x:?}): all rollouts of a set must \
                 share their external forces and measurement noise",
                path.display(),
                first.display()
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_cuts_regular_and_low_velocity_clips() {
        let cfg = ClipConfig {
            steps: Auto::Value(500),
            ..ClipConfig::default()
        };
        // 8 s at 1 ms: 8001 frames, velocities known from frame 0.
        let plan = cfg.plan("a.npz", 8001, 1e-3, 0);
        let regular: Vec<_> = plan
            .iter()
            .filter(|c| !c.low_velocity)
            .map(|c| c.start)
            .collect();
        let low: Vec<_> = plan
            .iter()
            .filter(|c| c.low_velocity)
            .map(|c| c.start)
            .collect();
        assert_eq!(regular.len(), 16);
        assert_eq!(regular[1], 500);
        assert_eq!(low, vec![7500, 7000]);
        let sub = ClipConfig {
            fraction: 0.25,
            low_velocity_fraction: 0.5,
            ..cfg.clone()
        };
        let a = sub.plan("a.npz", 8001, 1e-3, 0);
        assert_eq!(a, sub.plan("a.npz", 8001, 1e-3, 0), "deterministic");
        assert!(a.len() < plan.len());
    }

    #[test]
    fn sampler_visits_every_item_once_per_epoch() {
        let mut s = Sampler::new(10, 3);
        let mut seen = s.next(4);
        seen.extend(s.next(6));
        seen.sort();
        assert_eq!(seen, (0..10).collect::<Vec<_>>());
    }

    /// Hidden runs of at most `max_gap` frames with seen frames on both sides are bridged; a
    /// longer run, or one at either end of the track, is not.
    #[test]
    fn short_interior_gaps_are_bridged() {
        let frames = 12;
        let hidden = [0, 3, 5, 6, 8, 9, 10];
        let track = Track {
            frames,
            particles: 2,
            positions: vec![0.0; frames * 2 * 3],
            velocities: vec![0.0; frames * 2 * 3],
            stored_velocities: false,
            pinned: vec![false; 2],
            visible: Some(
                (0..frames)
                    .flat_map(|f| [!hidden.contains(&f), f != 11])
                    .collect(),
            ),
        };
        let bridged = track.bridged(2).expect("a mask");
        let of =
            |i: usize| -> Vec<usize> { (0..frames).filter(|&f| !bridged[f * 2 + i]).collect() };
        assert_eq!(of(0), vec![0, 8, 9, 10]);
        assert_eq!(of(1), vec![11]);
        assert_eq!(
            track.bridged(0).expect("a mask"),
            *track.visible.as_ref().unwrap()
        );
        let all_seen = Track {
            visible: None,
            ..track
        };
        assert!(all_seen.bridged(2).is_none());
    }
}
