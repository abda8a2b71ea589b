//! The latent-dynamics pipeline (paper 002): the implicit-Euler reference, the Burn incremental
//! potential against the host FEM energy and forces, the autoencoder, the integrator, the noise
//! and the plain-Rust inference path.

mod common;

use burn::tensor::{Device, Tensor, TensorData};
use rand::{SeedableRng, rngs::StdRng};
use springtime::cloth::triangles::V3;
use springtime::cloth::{GridSpec, Topology};
use springtime::export::SurrogateJson;
use springtime::latent::energy::Potential;
use springtime::latent::eval::{LatentModel, evaluate};
use springtime::latent::scenario::{ClothConfig, ScenarioConfig, ScenarioKind, Scene, generate};
use springtime::latent::subspace::SolveConfig;
use springtime::latent::surrogate::SpringSheet;
use springtime::latent::train::{TrainOptions, perturb, train};
use springtime::latent::{LatentConfig, integrator::LossKind};
use springtime::progress::Progress;
use springtime::settings::Job;
use springtime::source::implicit::{ImplicitEuler, NewtonConfig};

/// A 5 × 6 sheet of the paper's cloth, 0.2 m × 0.25 m.
fn small_cloth() -> ClothConfig {
    ClothConfig {
        nx: 5,
        ny: 6,
        width: 0.2,
        height: 0.25,
        ..ClothConfig::default()
    }
}

/// A deterministic, clearly deformed state of the sheet: stretched, sheared and curved.
fn deformed(cloth: &ClothConfig) -> Vec<V3> {
    cloth
        .rest_uv()
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let s = (i as f64 * 0.77).sin();
            [
                1.03 * p[0] + 0.02 * p[1] + 0.002 * s,
                0.98 * p[1] + 0.001 * (i as f64 * 1.3).cos(),
                0.04 * (3.0 * p[0]).sin() * p[1] + 0.003 * s,
            ]
        })
        .collect()
}

#[test]
fn burn_energy_and_forces_equal_the_host_fem() {
    let cloth = small_cloth();
    let fem = cloth.fem();
    let x = deformed(&cloth);
    let n = x.len();
    let device = Device::flex().autodiff();
    let potential = Potential::new(&fem, 1.0 / 30.0, &[0], 1e5, &device).unwrap();
    let flat: Vec<f32> = x.iter().flat_map(|p| p.map(|v| v as f32)).collect();
    let xt = Tensor::<3>::from_data(TensorData::new(flat, [1, n, 3]), &device).require_grad();
    let energy = potential.elastic(xt.clone());
    let burn_e = energy.clone().into_scalar::<f32>() as f64;
    let host_e = fem.energy(&x);
    assert!(host_e > 1e-3, "the state must be deformed: {host_e}");
    assert!(
        (burn_e - host_e).abs() <= 1e-4 * host_e,
        "energy: Burn {burn_e} vs host {host_e}"
    );
    let grads = energy.backward();
    let g: Vec<f32> = xt
        .grad(&grads)
        .unwrap()
        .into_data()
        .try_into_vec_as::<f32>()
        .unwrap();
    let mut forces = vec![[0.0; 3]; n];
    fem.internal_forces(&x, &vec![[0.0; 3]; n], &mut forces);
    let scale = forces.iter().flatten().fold(0.0f64, |m, f| m.max(f.abs()));
    for i in 0..n {
        for c in 0..3 {
            let (a, b) = (g[3 * i + c] as f64, -forces[i][c]);
            assert!(
                (a - b).abs() <= 1e-3 * scale,
                "∂E/∂x[{i}][{c}]: Burn {a} vs −force {b} (scale {scale})"
            );
        }
    }
}

#[test]
fn burn_incremental_potential_equals_the_host_step_objective() {
    let cloth = small_cloth();
    let fem = cloth.fem();
    let dt = 1.0 / 30.0;
    let stepper = ImplicitEuler::new(fem.clone(), dt, NewtonConfig::default()).unwrap();
    let x = deformed(&cloth);
    let x_tilde: Vec<V3> = x.iter().map(|p| [p[0] + 0.01, p[1], p[2] - 0.02]).collect();
    let n = x.len();
    let device = Device::flex();
    let pinned = [0usize, 4];
    let potential = Potential::new(&fem, dt, &pinned, 1e5, &device).unwrap();
    let t = |v: &[V3], rows: usize| {
        let flat: Vec<f32> = v.iter().flat_map(|p| p.map(|c| c as f32)).collect();
        Tensor::<3>::from_data(TensorData::new(flat, [1, rows, 3]), &device)
    };
    // Targets where the pinned vertices are: the soft boundary term is zero.
    let targets: Vec<V3> = pinned.iter().map(|&i| x[i]).collect();
    let burn = potential
        .incremental(t(&x, n), None, t(&x_tilde, n), t(&targets, 2))
        .into_scalar::<f32>() as f64;
    let host = stepper.potential(&x, &x_tilde);
    assert!(
        (burn - host).abs() <= 1e-4 * host.abs().max(1.0),
        "Φ: Burn {burn} vs host {host}"
    );
    // At x = x̃ without gravity the inertial term vanishes: Φ is the elastic energy.
    let still = ClothConfig {
        gravity: [0.0; 3],
        ..cloth.clone()
    };
    let p0 = Potential::new(&still.fem(), dt, &pinned, 1e5, &device).unwrap();
    let phi = p0
        .incremental(t(&x, n), None, t(&x, n), t(&targets, 2))
        .into_scalar::<f32>() as f64;
    let e = still.fem().energy(&x);
    assert!((phi - e).abs() <= 1e-4 * e, "Φ(x̃) {phi} vs E {e}");
}

#[test]
fn element_hessians_assemble_to_the_derivative_of_the_forces() {
    let cloth = small_cloth();
    let fem = cloth.fem();
    let x = deformed(&cloth);
    let n = x.len();
    let v: Vec<V3> = (0..n)
        .map(|i| {
            [
                (i as f64).sin(),
                (i as f64 * 0.3).cos(),
                (i as f64 * 1.7).sin(),
            ]
        })
        .collect();
    let mut hv = vec![[0.0; 3]; n];
    for block in fem.hessian_blocks(&x) {
        let m = 3 * block.vertices.len();
        for (r, &vr) in block.vertices.iter().enumerate() {
            for cr in 0..3 {
                for (c, &vc) in block.vertices.iter().enumerate() {
                    for cc in 0..3 {
                        hv[vr][cr] += block.matrix[(3 * r + cr) * m + 3 * c + cc] * v[vc][cc];
                    }
                }
            }
        }
    }
    let eps = 1e-6;
    let forces_at = |s: f64| {
        let y: Vec<V3> = (0..n)
            .map(|i| [0, 1, 2].map(|c| x[i][c] + s * v[i][c]))
            .collect();
        let mut f = vec![[0.0; 3]; n];
        fem.internal_forces(&y, &vec![[0.0; 3]; n], &mut f);
        f
    };
    let (fp, fm) = (forces_at(eps), forces_at(-eps));
    let scale = hv.iter().flatten().fold(0.0f64, |m, h| m.max(h.abs()));
    for i in 0..n {
        for c in 0..3 {
            let fd = -(fp[i][c] - fm[i][c]) / (2.0 * eps);
            assert!(
                (hv[i][c] - fd).abs() <= 1e-5 * scale,
                "(Hv)[{i}][{c}] {} vs {fd}",
                hv[i][c]
            );
        }
    }
}

#[test]
fn implicit_step_keeps_a_sheet_at_rest_at_rest() {
    let cloth = ClothConfig {
        gravity: [0.0; 3],
        ..small_cloth()
    };
    let stepper = ImplicitEuler::new(cloth.fem(), 1.0 / 30.0, NewtonConfig::default()).unwrap();
    let rest: Vec<V3> = cloth.rest_uv().iter().map(|p| [p[0], p[1], 0.0]).collect();
    let (x, report) = stepper.step(&rest, &rest, &[0], &[rest[0]]).unwrap();
    assert_eq!(report.iterations, 0);
    for (a, b) in x.iter().zip(&rest) {
        assert_eq!(a, b);
    }
}

#[test]
fn implicit_euler_dissipates_and_newton_meets_its_tolerance() {
    // A free, deformed sheet without gravity: kinetic + elastic energy must not grow.
    let cloth = ClothConfig {
        gravity: [0.0; 3],
        ..small_cloth()
    };
    let fem = cloth.fem();
    let dt = 1.0 / 30.0;
    let newton = NewtonConfig {
        tolerance: 1e-6,
        max_iterations: 100,
        ..NewtonConfig::default()
    };
    let stepper = ImplicitEuler::new(fem.clone(), dt, newton).unwrap();
    let start = deformed(&cloth);
    let (mut prev2, mut prev) = (start.clone(), start);
    let total = |x: &[V3], xp: &[V3]| {
        let kinetic: f64 = x
            .iter()
            .zip(xp)
            .zip(fem.masses())
            .map(|((a, b), m)| 0.5 * m * (0..3).map(|c| ((a[c] - b[c]) / dt).powi(2)).sum::<f64>())
            .sum();
        kinetic + fem.energy(x)
    };
    let mut energy = total(&prev, &prev2);
    // The residual bound the solver promises: tolerance × the heaviest vertex's weight, with
    // |g| counted as at least 1 m/s².
    let heaviest = fem.masses().iter().copied().fold(0.0, f64::max);
    for step in 0..40 {
        let (x, report) = stepper.step(&prev, &prev2, &[], &[]).unwrap();
        assert!(
            report.residual <= newton.tolerance * heaviest,
            "step {step}: {report:?}"
        );
        let e = total(&x, &prev);
        assert!(
            e <= energy * (1.0 + 1e-9),
            "step {step}: energy grew {energy} → {e}"
        );
        energy = e;
        prev2 = std::mem::replace(&mut prev, x);
    }
    assert!(
        energy < 0.9 * total(&deformed(&cloth), &deformed(&cloth)),
        "no dissipation"
    );
}

#[test]
fn perturbation_is_zero_without_noise_and_scaled_by_the_batch_deviation() {
    let rows: Vec<Vec<f32>> = (0..64)
        .map(|i| vec![(i as f32 * 0.37).sin(), 3.0 * (i as f32 * 0.11).cos(), 7.0])
        .collect();
    let mut rng = StdRng::seed_from_u64(1);
    assert_eq!(perturb(&rows, 2, 0.0, &mut rng), rows);
    let noisy = perturb(&rows, 2, 0.1, &mut rng);
    for k in 0..2 {
        let m = rows.iter().map(|r| r[k]).sum::<f32>() / 64.0;
        let std = (rows.iter().map(|r| (r[k] - m).powi(2)).sum::<f32>() / 64.0).sqrt();
        let biggest = rows
            .iter()
            .zip(&noisy)
            .map(|(a, b)| (a[k] - b[k]).abs())
            .fold(0.0f32, f32::max);
        assert!(
            biggest <= 0.1 * std * 1.0001,
            "coordinate {k}: {biggest} vs σ {std}"
        );
        assert!(
            biggest >= 0.05 * std,
            "coordinate {k}: noise too small {biggest}"
        );
    }
    // The boundary features (past `dims`) are left alone.
    assert!(rows.iter().zip(&noisy).all(|(a, b)| a[2] == b[2]));
}

/// A tiny end-to-end job: 5 × 6 sheet, moving corners, 60 frames (40 train).
fn tiny_config(loss: LossKind) -> LatentConfig {
    let mut cfg: LatentConfig = toml::from_str("").unwrap();
    cfg.cloth = small_cloth();
    cfg.scenario = ScenarioConfig {
        frames: 60,
        amplitude: 0.05,
        frequency: 0.8,
        ..ScenarioConfig::default()
    };
    cfg.autoencoder.latent = 3;
    cfg.autoencoder.pca_modes = 10;
    cfg.autoencoder.hidden = vec![32, 32];
    cfg.autoencoder.epochs = 400;
    cfg.autoencoder.batch = 40;
    cfg.integrator.hidden = vec![32, 32];
    cfg.integrator.epochs = 300;
    cfg.integrator.batch = 38;
    cfg.integrator.train_frames = 40;
    cfg.integrator.loss = loss;
    cfg
}

/// Trains `cfg` into `dir` (no --force).
fn train_in(
    dir: &std::path::Path,
    cfg: &LatentConfig,
) -> anyhow::Result<springtime::latent::train::LatentMeta> {
    train(
        cfg,
        &TrainOptions {
            out: dir.to_path_buf(),
            data: None,
            force: false,
            autoencoder_from: None,
            from: None,
        },
        &Progress::quiet(),
    )
}

/// Trains `cfg` in a fresh directory for the test `name`: the directory (removed when dropped),
/// the training's record and the saved model, opened.
fn trained(
    name: &str,
    cfg: &LatentConfig,
) -> (
    common::TestDir,
    springtime::latent::train::LatentMeta,
    LatentModel,
) {
    let dir = common::temp_dir(name);
    let meta = train_in(&dir, cfg).unwrap();
    let model = LatentModel::open(&dir).unwrap();
    (dir, meta, model)
}

#[test]
fn the_moving_corner_scene_follows_its_path_and_generates_a_rollout() {
    let cfg = tiny_config(LossKind::SelfSupervised);
    let scene = Scene::new(&cfg.cloth, &cfg.scenario);
    assert_eq!(scene.pinned, vec![0, 4]);
    let (rollout, stats) = generate(&cfg.cloth, &scene, cfg.solver, &Progress::quiet()).unwrap();
    assert_eq!(rollout.frames, 60);
    assert!(stats.mean_iterations >= 1.0);
    for f in [0, 17, 59] {
        for (k, &i) in scene.pinned.iter().enumerate() {
            let p = rollout.position(f, i);
            let t = scene.targets(f)[k];
            for c in 0..3 {
                assert!((p[c] as f64 - t[c]).abs() < 1e-6, "frame {f} pin {i}");
            }
        }
    }
    // The sheet hangs: its lowest row ends below the pins.
    let low = rollout.position(59, 29)[2];
    assert!(low < -0.2, "lowest vertex at z = {low}");
    let cantilever = Scene::new(
        &cfg.cloth,
        &ScenarioConfig {
            kind: ScenarioKind::Cantilever,
            ..cfg.scenario.clone()
        },
    );
    assert_eq!(cantilever.pinned, (0..5).collect::<Vec<_>>());
    assert_eq!(cantilever.targets(30), cantilever.targets(0));
}

#[test]
fn a_tiny_latent_model_trains_reconstructs_rolls_out_and_matches_its_plain_rust_copy() {
    let cfg = tiny_config(LossKind::SelfSupervised);
    let (dir, meta, model) = trained("latent", &cfg);
    // The autoencoder reconstructs the training frames to well below the motion's extent
    // (the corners move ±5 cm; the sheet swings by more).
    assert!(
        meta.reconstruction_rmse_train < 3e-3,
        "reconstruction RMSE {} m",
        meta.reconstruction_rmse_train
    );
    // The saved autoencoder (BatchNorm statistics included) reconstructs as the trained one did.
    let r = &model.reference;
    let latents = &model.latents;
    let decoded = springtime::latent::train::decode(
        &model.autoencoder.decoder,
        &latents[..cfg.integrator.train_frames],
        &model.device,
    );
    let se: f64 = decoded
        .iter()
        .enumerate()
        .map(|(f, y)| {
            let rel = r.relative(f);
            rel.iter()
                .zip(y)
                .map(|(a, b)| (a - *b as f64).powi(2))
                .sum::<f64>()
        })
        .sum();
    let reloaded = (se / (decoded.len() * r.frames[0].len()) as f64).sqrt();
    assert!(
        (reloaded - meta.reconstruction_rmse_train).abs() <= 1e-4 * reloaded,
        "reloaded RMSE {reloaded} vs trained {}",
        meta.reconstruction_rmse_train
    );
    // Plain-Rust encoder and decoder = Burn's.
    let frame: Vec<f32> = r.relative(7).iter().map(|&v| v as f32).collect();
    let plain_z = model.plain.encoder.eval(&frame);
    for (a, b) in plain_z.iter().zip(&latents[7]) {
        assert!(
            (a - b).abs() <= 1e-4 * (1.0 + b.abs()),
            "encoder {a} vs {b}"
        );
    }
    let z: Vec<f32> = vec![0.3, -0.7, 1.1];
    let burn = model.decode_burn(&z);
    let plain = model.plain.decoder.eval(&model.scales.restore(&z));
    for (a, b) in burn.iter().zip(&plain) {
        assert!(
            (a - b).abs() <= 1e-5 * (1.0 + a.abs()),
            "decoder {a} vs {b}"
        );
    }
    let report = evaluate(&dir, false, None).unwrap();
    assert_eq!(report.frames, 20);
    assert!(!report.diverged);
    assert!(report.pinned_max_error < 5e-3, "{report:?}");
    assert!(dir.join("latent_eval.json").exists());
    // A finished run is not overwritten without --force.
    let again = train_in(&dir, &cfg);
    assert!(format!("{:#}", again.unwrap_err()).contains("--force"));
}

#[test]
fn the_supervised_integrator_overfits_a_short_sequence() {
    let mut cfg = tiny_config(LossKind::Supervised);
    // Overfitting 38 steps takes a few thousand Adam steps.
    cfg.integrator.epochs = 2000;
    let (_dir, _, model) = trained("latent-supervised", &cfg);
    // One-step predictions on the training frames, from the encoded reference.
    let latents = &model.latents;
    let l = cfg.autoencoder.latent;
    let mut scratch = (Vec::new(), Vec::new());
    let (mut err, mut spread) = (0.0f64, 0.0f64);
    for t in 2..cfg.integrator.train_frames {
        let z = model.plain.step(&model.teacher_input(t), l, &mut scratch);
        let truth = model.scales.standardise(&latents[t]);
        err += z
            .iter()
            .zip(&truth)
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum::<f64>();
        spread += truth.iter().map(|v| (*v as f64).powi(2)).sum::<f64>();
    }
    // The standardised latents have unit variance: the fit explains > 99 % of it.
    assert!(
        err < 0.01 * spread,
        "one-step error {err} vs spread {spread}"
    );
}

#[test]
fn solved_steps_minimise_the_potential_and_the_solved_integrator_learns_them() {
    let mut cfg = tiny_config(LossKind::Solved);
    cfg.integrator.epochs = 800;
    cfg.integrator.rounds = 2;
    let (_dir, meta, model) = trained("latent-solved", &cfg);
    assert_eq!(meta.integrator.epochs, 1600, "two rounds of 800 epochs");
    let solve = SolveConfig::default();
    let l = cfg.autoencoder.latent;
    let mut scratch = (Vec::new(), Vec::new());
    let (mut err, mut spread) = (0.0f64, 0.0f64);
    // The minimum over the decoder's manifold lies no higher than the encoded reference
    // frame, on training and on unseen frames.
    for t in [4, 22, 38, 45, 57] {
        let step = model.solve_step(t, &solve).unwrap();
        let tol = 1e-5 * step.potential.abs().max(1.0);
        assert!(
            step.potential <= step.potential_at_reference + tol,
            "step {t}: {step:?}"
        );
    }
    // The integrator trained on solved steps fits its training minimisers far better than the
    // extrapolation the search starts from.
    for t in [4, 13, 22, 31, 38] {
        let step = model.solve_step(t, &solve).unwrap();
        let input = model.teacher_input(t);
        let z = model.plain.step(&input, l, &mut scratch);
        for k in 0..l {
            let guess = 2.0 * input[k] - input[l + k];
            err += ((z[k] - step.latent[k]) as f64).powi(2);
            spread += ((guess - step.latent[k]) as f64).powi(2);
        }
    }
    assert!(
        err < 0.25 * spread,
        "integrator error {err} vs the extrapolation's {spread}"
    );
}

/// Writes a job of the command-line tests to `dir/<file>`: `head`, then the small networks they
/// train, with `integrator` (keys) added to the integrator's table. Returns its path and the
/// run folder, `dir/run`.
fn write_job(
    dir: &std::path::Path,
    file: &str,
    head: &str,
    integrator: &str,
) -> (std::path::PathBuf, std::path::PathBuf) {
    let text = format!(
        r#"{head}
[autoencoder]
latent = 2
pca_modes = 6
hidden = [16, 16]
epochs = 50
batch = 30
[integrator]
hidden = [16]
batch = 28
train_frames = 30
{integrator}
"#
    );
    std::fs::write(dir.join(file), text).unwrap();
    (dir.join(file), dir.join("run"))
}

/// `springtime latent bench <run> --full-frames 3` in `dir`: the JSON line it prints.
fn bench(run: &str, dir: &std::path::Path) -> serde_json::Value {
    let out = common::ok(&common::springtime(
        &["latent", "bench", run, "--full-frames", "3"],
        dir,
    ));
    let stdout = out.lines().rev().find(|l| l.starts_with('{')).unwrap();
    serde_json::from_str(stdout).unwrap()
}

#[test]
fn the_latent_commands_train_evaluate_and_bench_from_a_config() {
    let dir = common::temp_dir("latent-cli");
    let (config, run) = write_job(
        &dir,
        "tiny.toml",
        r#"
name = "tiny"
[cloth]
nx = 4
ny = 5
width = 0.15
height = 0.2
[scenario]
frames = 40
amplitude = 0.04"#,
        "epochs = 20",
    );
    let run_s = run.to_str().unwrap();
    let cfg_s = config.to_str().unwrap();
    common::ok(&common::springtime(
        &["latent", "train", cfg_s, "--out", run_s],
        &dir,
    ));
    common::ok(&common::springtime(
        &[
            "latent",
            "eval",
            run_s,
            "--subspace",
            "--solve-iterations",
            "5",
        ],
        &dir,
    ));
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("latent_eval.json")).unwrap())
            .unwrap();
    assert_eq!(eval["frames"], 10);
    for key in [
        "diverged",
        "rmse",
        "max_error",
        "pinned_max_error",
        "rest_rmse_last_50",
        "rest_motion_last_50",
    ] {
        assert!(!eval[key].is_null(), "latent_eval.json lacks {key}");
    }
    assert_eq!(eval["subspace"]["solve"]["iterations"], 5);
    assert_eq!(
        eval["subspace"]["rmse_per_frame"].as_array().unwrap().len(),
        10
    );
    let bench = bench(run_s, &dir);
    assert!(bench["latent_us_per_frame"].as_f64().unwrap() > 0.0);
    assert!(bench["full_us_per_frame"].as_f64().unwrap() > 0.0);
    assert!(bench["solved_us_per_frame"].as_f64().unwrap() > 0.0);
    // A finished run is refused without --force, and a typo names the key.
    let again = common::springtime(&["latent", "train", cfg_s, "--out", run_s], &dir);
    assert!(!again.status.success());
    let retrain = |set: &str| {
        common::springtime(
            &[
                "latent", "train", cfg_s, "--out", run_s, "--force", "--set", set,
            ],
            &dir,
        )
    };
    let bad = retrain("integrator.nosie=0");
    assert!(String::from_utf8_lossy(&bad.stderr).contains("nosie"));
    // More PCA modes than training frames is refused up front, naming both keys.
    let short = retrain("autoencoder.pca_modes=31");
    let err = String::from_utf8_lossy(&short.stderr);
    assert!(
        !short.status.success() && err.contains("pca_modes") && err.contains("train_frames"),
        "{err}"
    );
}

/// A small spring surrogate (4 × 5 grid over 0.3 m × 0.4 m, springs of every family with
/// varied `k` and `b`) as an exported `surrogate.json` would hold it.
fn small_surrogate() -> SurrogateJson {
    let topo = Topology::grid(
        &GridSpec {
            nx: 4,
            ny: 5,
            shear_main: true,
            shear_anti: true,
            bending_stride: 2,
            ..GridSpec::default()
        },
        0.3,
        0.4,
    );
    let s = topo.num_springs();
    SurrogateJson {
        rayleigh: 0.05,
        dt: Some(1e-3),
        ..SurrogateJson::springs(
            &topo,
            vec![0.01; topo.num_particles()],
            (0..s).map(|i| 15.0 + (i % 7) as f32 * 3.0).collect(),
            (0..s).map(|i| 0.02 + (i % 5) as f32 * 0.01).collect(),
        )
    }
}

#[test]
fn the_spring_potential_differentiates_to_the_surrogates_forces() {
    let sheet = SpringSheet {
        surrogate: small_surrogate(),
        source: "test".into(),
    };
    let topo = sheet.topology();
    let device = Device::flex();
    let ad = device.clone().autodiff();
    let dt = 1.0 / 30.0;
    let potential = Potential::springs(&sheet, dt, &[0, 3], 1e5, &ad);
    let n = topo.num_particles();
    let x: Vec<V3> = topo
        .rest_positions()
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let s = (i as f64 * 0.9).sin();
            [
                1.05 * p[0] + 0.01 * s,
                0.97 * p[1],
                0.03 * s + 0.05 * p[0] * p[1],
            ]
        })
        .collect();
    let x_prev: Vec<V3> = x
        .iter()
        .enumerate()
        .map(|(i, p)| {
            [
                p[0] - 0.004 * (i as f64).cos(),
                p[1] + 0.003,
                p[2] - 0.002 * (i % 3) as f64,
            ]
        })
        .collect();
    let t = |v: &[V3], dev: &Device| {
        let flat: Vec<f32> = v.iter().flat_map(|p| p.map(|c| c as f32)).collect();
        Tensor::<3>::from_data(TensorData::new(flat, [1, n, 3]), dev)
    };
    let grad_of = |which: &dyn Fn(Tensor<3>) -> Tensor<1>| -> Vec<f32> {
        let xt = t(&x, &ad).require_grad();
        let e = which(xt.clone()).sum();
        xt.grad(&e.backward())
            .unwrap()
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap()
    };
    let net = sheet.net(&device);
    let zeros = Tensor::<1>::zeros([topo.num_springs()], &device);
    let host = |f: Tensor<3>| f.into_data().try_into_vec_as::<f32>().unwrap();
    // −∂E/∂x is the springs' elastic force (Eq. 4 with b = 0) at x.
    let elastic = grad_of(&|x| potential.elastic(x));
    let f_elastic = host(net.graph.spring_forces_reference(
        t(&x, &device),
        t(&x, &device).zeros_like(),
        net.k.val(),
        zeros.clone(),
    ));
    // −∂D/∂x is the dashpots' force at x_prev with the step's velocity (x − x_prev)/h, plus
    // Rayleigh's −c v.
    let v: Vec<V3> = x
        .iter()
        .zip(&x_prev)
        .map(|(a, b)| [0, 1, 2].map(|k| (a[k] - b[k]) / dt))
        .collect();
    let xp = t(&x_prev, &ad);
    let damping = grad_of(&|x| potential.dissipation(x, xp.clone()));
    let f_damping: Vec<f32> = host(net.graph.spring_forces_reference(
        t(&x_prev, &device),
        t(&v, &device),
        zeros,
        net.b.val(),
    ))
    .iter()
    .zip(v.iter().flatten())
    .map(|(f, v)| f - 0.05 * *v as f32)
    .collect();
    for (name, grad, force) in [
        ("elastic", elastic, f_elastic),
        ("damping", damping, f_damping),
    ] {
        let scale = force.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(scale > 1e-3, "{name}: the test state exerts no force");
        for (i, (g, f)) in grad.iter().zip(&force).enumerate() {
            assert!(
                (g + f).abs() <= 1e-3 * scale,
                "{name} ∂/∂x[{i}]: {g} vs −force {f} (scale {scale})"
            );
        }
    }
}

#[test]
fn a_spring_surrogate_distils_into_a_latent_model_from_its_surrogate_json() {
    let dir = common::temp_dir("latent-distill");
    let json = dir.join("surrogate.json");
    std::fs::write(&json, small_surrogate().to_text().unwrap()).unwrap();
    let (config, run) = write_job(
        &dir,
        "distill.toml",
        r#"
name = "distill"
[scenario]
frames = 40
amplitude = 0.05"#,
        "epochs = 100\nrounds = 1\nnoisy_copies = 1",
    );
    let (run_s, cfg_s, json_s) = (
        run.to_str().unwrap(),
        config.to_str().unwrap(),
        json.to_str().unwrap(),
    );
    common::ok(&common::springtime(
        &["latent", "train", cfg_s, "--from", json_s, "--out", run_s],
        &dir,
    ));
    // The run keeps the surrogate and takes its grid for the sheet.
    assert!(run.join("surrogate.json").exists());
    let saved = LatentConfig::load(&run.join("config.toml"), &[]).unwrap();
    assert_eq!((saved.cloth.nx, saved.cloth.ny), (4, 5));
    assert_eq!((saved.cloth.width, saved.cloth.height), (0.3, 0.4));
    // The reference is the surrogate's own motion: simulated again with its stepper from the
    // same start, frame 12 is reproduced, and the pinned corners follow their path.
    let model = LatentModel::open(&run).unwrap();
    let r = &model.reference;
    let sheet = SpringSheet::open(&run.join("surrogate.json")).unwrap();
    let scene = Scene::new(&saved.cloth, &saved.scenario);
    assert_eq!(r.pinned, scene.pinned);
    let still = vec![[0.0; 3]; r.frames[0].len()];
    let again = sheet
        .stepper(r.dt)
        .unwrap()
        .roll(
            (&r.frames[0], &still),
            &r.pinned,
            &|f| scene.targets(f),
            12,
            None,
        )
        .unwrap();
    for (a, b) in again[11].iter().zip(&r.frames[12]) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-5, "{a:?} vs {b:?}");
        }
    }
    let moved = (0..3)
        .map(|k| (r.frames[12][5][k] - r.frames[0][5][k]).abs())
        .sum::<f64>();
    assert!(moved > 1e-3, "the free vertex 5 did not move: {moved}");
    // The spring potential drives the solved steps: their minimum lies no higher than the
    // encoded reference frame's.
    let step = model.solve_step(33, &SolveConfig::default()).unwrap();
    assert!(
        step.potential <= step.potential_at_reference + 1e-5 * step.potential.abs().max(1.0),
        "{step:?}"
    );
    common::ok(&common::springtime(&["latent", "eval", run_s], &dir));
    let bench = bench(run_s, &dir);
    assert!(bench["full_us_per_frame"].as_f64().unwrap() > 0.0);
    assert_eq!(
        bench["full_newton_iterations"], 0.0,
        "the surrogate steps explicitly"
    );
    // A reference the surrogate did not make (the FEM cloth's, on the same grid) is refused,
    // and the finished run is left as it was.
    let fem = dir.join("fem");
    common::ok(&common::springtime(
        &[
            "latent",
            "generate",
            cfg_s,
            "--out",
            fem.to_str().unwrap(),
            "--set",
            "cloth.nx=4",
            "--set",
            "cloth.ny=5",
        ],
        &dir,
    ));
    let fem_rollout = fem.join("rollout.npz");
    let mixed = common::springtime(
        &[
            "latent",
            "train",
            cfg_s,
            "--from",
            json_s,
            "--data",
            fem_rollout.to_str().unwrap(),
            "--out",
            run_s,
            "--force",
        ],
        &dir,
    );
    common::fails(&mixed, &["was not simulated by the surrogate"]);
    assert!(run.join("latent.json").exists());
    // Surrogate files whose arrays disagree, or whose rest lengths are not the grid's, are
    // refused, naming the file and the key.
    let mut short = small_surrogate();
    short.k.pop();
    let mut stretched = small_surrogate();
    stretched.rest_length[3] *= 1.1;
    for (bad, key) in [(short, "`k`"), (stretched, "`rest_length`")] {
        std::fs::write(&json, bad.to_text().unwrap()).unwrap();
        let refused = common::springtime(
            &[
                "latent", "train", cfg_s, "--from", json_s, "--out", run_s, "--force",
            ],
            &dir,
        );
        common::fails(&refused, &["surrogate.json", key]);
    }
}
