//! The FEM source's step on `configs/table2_fem.toml`'s sheet (31 × 31, co-rotational
//! membrane, bending, strain-rate damping), at a state 1.5 s into a pinned rollout: the net
//! forces alone and one semi-implicit Euler step. Run with `cargo bench --bench fem_step`.

use criterion::{Criterion, criterion_group, criterion_main};
use rand::{SeedableRng, rngs::StdRng};
use springtime::source::{ClothSim, FemCloth, Layout, Scenario, SourceConfig, SourceKind};

fn table2() -> SourceConfig {
    let mut cfg = SourceConfig {
        kind: SourceKind::Fem,
        nx: 31,
        ny: 31,
        stiffness_levels: vec![100.0, 400.0, 1000.0],
        layout: Layout::Patches,
        anchor_radius: 0.8,
        ..SourceConfig::default()
    };
    cfg.fem.strain_damping = 0.004;
    cfg
}

fn bench(c: &mut Criterion) {
    let cfg = table2();
    let cloth = FemCloth::from_config(&cfg);
    let scenario = Scenario::random(
        cloth.rest_uv(),
        cfg.anchor_radius,
        &mut StdRng::seed_from_u64(3),
    );
    let mut x = scenario.initial_positions(cloth.rest_uv());
    let mut v = vec![[0.0; 3]; x.len()];
    let mut scratch = Vec::new();
    for _ in 0..1500 {
        cloth.step(&mut x, &mut v, &scenario.pinned, cfg.dt, None, &mut scratch);
    }
    let mut group = c.benchmark_group("fem_31x31");
    let mut out = vec![[0.0; 3]; x.len()];
    group.bench_function("net_forces", |b| {
        b.iter(|| cloth.net_forces(&x, &v, &mut out))
    });
    group.bench_function("step", |b| {
        let (mut y, mut w) = (x.clone(), v.clone());
        b.iter(|| cloth.step(&mut y, &mut w, &scenario.pinned, cfg.dt, None, &mut scratch))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
