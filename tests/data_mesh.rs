//! The surrogate on the data's own mesh (`cloth.layout = "data"`): a spring cloth on an
//! irregular point set, whose per-spring stiffness a grid cannot hold, is recovered when the
//! surrogate's particles and springs are the data's.

mod common;

use rand::{SeedableRng, rngs::StdRng};
use springtime::cloth::Topology;
use springtime::config::Config;
use springtime::data::Rollout;
use springtime::progress::Progress;
use springtime::settings::Job;
use springtime::source::{Scenario, SpringCloth, simulate_rollout};
use springtime::train::{TrainOptions, train};

#[test]
fn a_data_mesh_surrogate_recovers_the_stiffness_of_an_irregular_spring_cloth() {
    let dir = common::temp_dir("data_mesh");
    let n = 8;
    let cfg = common::source(n, &[20.0, 80.0], 1.0);
    let size = 0.5 * (n - 1) as f64;
    let uv = common::jittered_points(n, 7);
    // The truth: springs on the Delaunay mesh of the points (edges and hinges), soft on the
    // left half and stiff on the right, as `layout = "data"` will rebuild them from the points.
    let topology = Topology::of_points(&uv, size, size, true).unwrap();
    let base = SpringCloth::from_config(&cfg);
    let k: Vec<f64> = (0..topology.num_springs())
        .map(|s| {
            if topology.midpoint(s)[0] < 0.5 * size {
                20.0
            } else {
                80.0
            }
        })
        .collect();
    let truth = SpringCloth {
        k: k.clone(),
        b: vec![6.0; topology.num_springs()],
        mass: base.mass,
        topology,
        ..base
    };
    let (data, test) = (dir.join("train"), dir.join("test"));
    std::fs::create_dir_all(&data).unwrap();
    std::fs::create_dir_all(&test).unwrap();
    for seed in 0..18u64 {
        let scenario = Scenario::random(
            &truth.topology.rest_uv,
            cfg.anchor_radius,
            &mut StdRng::seed_from_u64(seed),
        );
        let name = format!("r{seed:02}.npz");
        let r: Rollout = simulate_rollout(&truth, &cfg, &scenario, None, &name).unwrap();
        assert!(r.mesh.is_none(), "the points come without a mesh");
        r.save(&if seed < 16 { &data } else { &test }.join(&name))
            .unwrap();
    }

    let text = |layout: &str| {
        format!(
            "name = \"{layout}\"\n[cloth]\nlayout = \"{layout}\"\nnx = {n}\nny = {n}\n{}",
            common::RECOVERY
        )
    };
    let run = |layout: &str| {
        let mut config = Config::parse(&text(layout), &[]).unwrap();
        config.data.dir = data.clone();
        config.data.test_dir = Some(test.clone());
        config.runs_dir = dir.join("runs");
        train(&config, &TrainOptions::default(), &Progress::quiet()).unwrap()
    };
    let mesh = run("data");
    let (rmse_k, rmse_b) = (mesh.rmse_k.unwrap(), mesh.rmse_b.unwrap());
    eprintln!("data mesh: rmse_k {rmse_k:.3} N/m, rmse_b {rmse_b:.3} N·s/m");
    // From a uniform 50 N/m (RMSE 30 N/m) and 3 N·s/m: as the grid recovery test's tolerance.
    assert!(rmse_k < 5.0, "rmse_k = {rmse_k}");
    assert!(rmse_b < 1.5, "rmse_b = {rmse_b}");
    // A grid over the same points has no per-spring truth to compare with: its particles are
    // interpolated between the points.
    let grid = run("grid");
    assert!(grid.rmse_k.is_none());

    // The run opens again with its mesh: eval on the test split reproduces the trained figures.
    let opened = springtime::run::Run::open(&dir.join("runs").join("data"), &[], None).unwrap();
    assert_eq!(opened.topology.grid, None);
    assert_eq!(opened.topology.num_springs(), truth.topology.num_springs());
    assert_eq!(opened.topology.springs, truth.topology.springs);
    // With the masses it trained with (lumped; from the run's f32 `rest_uv`), or those its
    // config is opened with.
    let (reread, lumped) = (
        opened.topology.mass_weight.as_ref().unwrap(),
        truth.topology.mass_weight.as_ref().unwrap(),
    );
    assert!(reread.iter().zip(lumped).all(|(a, b)| (a - b).abs() < 1e-6));
    let equal = ["cloth.masses=\"equal\"".to_string()];
    let reopened =
        springtime::run::Run::open(&dir.join("runs").join("data"), &equal, None).unwrap();
    assert_eq!(reopened.topology.mass_weight, None);
    assert_eq!(reopened.topology.springs, truth.topology.springs);
}

/// The surrogate on a data mesh with the true `k`, `b` (tensor ops and the fused kernel, f32)
/// follows the host spring cloth whose particles carry the same masses (f64) — the mesh's lumped
/// masses, or equal ones (`cloth.masses`): the spring forces divided by the relative masses are
/// that cloth's dynamics. With the other masses, the same network drifts away.
#[test]
fn a_data_mesh_surrogate_with_the_true_springs_follows_a_source_of_its_masses() {
    use springtime::cloth::{ParticleMasses, Resampler};
    use springtime::data::Track;
    use springtime::model::{Kernel, SpringNet};
    use springtime::sim::Physics;
    let n = 7;
    let cfg = common::source(n, &[20.0, 80.0], 0.5);
    let size = 0.5 * (n - 1) as f64;
    let lumped = Topology::of_points(&common::jittered_points(n, 3), size, size, true).unwrap();
    let w = lumped.mass_weight.clone().unwrap();
    let spread = w.iter().fold(0.0f64, |m, w| m.max((w - 1.0).abs()));
    assert!(spread > 0.3, "lumped masses should differ: {spread}");
    let base = SpringCloth::from_config(&cfg);
    let s = lumped.num_springs();
    let k: Vec<f64> = (0..s)
        .map(|i| 30.0 + 20.0 * (i as f64 * 0.7).sin())
        .collect();
    let device = burn::tensor::Device::flex();
    for (host, other) in [
        (ParticleMasses::Lumped, ParticleMasses::Equal),
        (ParticleMasses::Equal, ParticleMasses::Lumped),
    ] {
        let truth = SpringCloth {
            k: k.clone(),
            b: vec![4.0; s],
            mass: base.mass,
            topology: lumped.clone().with_masses(host),
            ..base.clone()
        };
        let scenario = Scenario::random(
            &truth.topology.rest_uv,
            cfg.anchor_radius,
            &mut StdRng::seed_from_u64(5),
        );
        let r = simulate_rollout(&truth, &cfg, &scenario, None, "parity").unwrap();
        let track = Track::new(&r, &Resampler::new(&r.rest_uv, &truth.topology.rest_uv));
        let frames = r.frames - 1;
        let physics = Physics {
            frame_dt: r.frame_dt,
            substeps: (r.frame_dt / cfg.dt).round() as usize,
            mass: truth.mass,
            rayleigh: truth.rayleigh,
            gravity: truth.gravity,
            viscosity: 0.0,
            shear_compression: 1.0,
        };
        let gap = |masses: ParticleMasses, kernel: Kernel| {
            let topology = truth.topology.clone().with_masses(masses);
            let model = SpringNet::new(&topology, &truth.k, &truth.b, &device).with_kernel(kernel);
            common::last_frame(&model, &physics, None, &track, frames, &device)
                .iter()
                .zip(r.positions[frames * r.landmarks * 3..].iter())
                .map(|(a, b)| (a - b).abs() as f64)
                .fold(0.0, f64::max)
        };
        let moved = r.positions[frames * r.landmarks * 3..]
            .iter()
            .zip(&r.positions[..r.landmarks * 3])
            .map(|(a, b)| (a - b).abs() as f64)
            .fold(0.0, f64::max);
        let (fused, reference, mismatched) = (
            gap(host, Kernel::Fused),
            gap(host, Kernel::Reference),
            gap(other, Kernel::Fused),
        );
        eprintln!(
            "{host:?} host: moved {moved:.3} m; gap fused {fused:.2e}, reference {reference:.2e}, \
             {other:?} masses {mismatched:.2e} m"
        );
        assert!(moved > 0.1, "the cloth barely moved: {moved} m");
        assert!(
            fused < 1e-4 && reference < 1e-4,
            "{host:?} host: fused {fused} m, reference {reference} m"
        );
        assert!(
            mismatched > 10.0 * fused.max(1e-4),
            "{host:?} host, {other:?} masses: {mismatched} m"
        );
    }
}

/// Bad meshes for `layout = "data"`: a landmark in no triangle is refused naming the file and
/// the landmark, before any training.
#[test]
fn a_landmark_outside_the_mesh_is_refused_naming_the_file() {
    use springtime::data::MeshTruth;
    let dir = common::temp_dir("data_mesh_bad");
    let cfg = common::source(4, &[20.0], 0.1);
    let (_, mut r) = common::rollout(&cfg, 0);
    let grid = common::grid_of(&cfg);
    // Every cell but the last: landmark 15 (the far corner) is in no triangle.
    let mut triangles = grid.triangles.clone();
    triangles.retain(|t| !t.contains(&15));
    r.mesh = Some(MeshTruth {
        triangles,
        stiffness: None,
    });
    std::fs::create_dir_all(dir.join("data")).unwrap();
    r.save(&dir.join("data/holey.npz")).unwrap();
    let mut config = Config::parse("name = \"bad\"\n[cloth]\nlayout = \"data\"\n", &[]).unwrap();
    config.data.dir = dir.join("data");
    config.runs_dir = dir.join("runs");
    let err = format!(
        "{:#}",
        train(&config, &TrainOptions::default(), &Progress::quiet()).unwrap_err()
    );
    assert!(
        err.contains("holey.npz") && err.contains("landmark 15 is in no triangle"),
        "{err}"
    );
    // Files of one set must share their mesh.
    let (_, mut other) = common::rollout(&cfg, 1);
    other.mesh = Some(MeshTruth {
        triangles: grid.triangles.clone(),
        stiffness: None,
    });
    std::fs::create_dir_all(dir.join("mixed")).unwrap();
    r.save(&dir.join("mixed/a.npz")).unwrap();
    other.save(&dir.join("mixed/b.npz")).unwrap();
    config.data.dir = dir.join("mixed");
    config.cloth.layout = springtime::cloth::SpringLayout::Grid;
    let err = format!(
        "{:#}",
        train(&config, &TrainOptions::default(), &Progress::quiet()).unwrap_err()
    );
    assert!(
        err.contains("b.npz") && err.contains("`triangles` differs"),
        "{err}"
    );
    // `data check` refuses such a set too.
    let err = format!(
        "{:#}",
        springtime::check::check_dir(&dir.join("mixed"), &config).unwrap_err()
    );
    assert!(
        err.contains("b.npz") && err.contains("`triangles` differs"),
        "{err}"
    );
    // And a baseline cannot take the data's mesh.
    let err = Config::parse(
        "[cloth]\nlayout = \"data\"\n[model]\nkind = \"neural_ode\"\n",
        &[],
    )
    .unwrap_err();
    assert!(format!("{err:#}").contains("cloth.layout"), "{err:#}");
}
