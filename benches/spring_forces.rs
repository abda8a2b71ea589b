//! The spring-force op alone on the paper's 32 × 32 cloth (5,826 springs): the fused CPU
//! kernel called directly, and through Burn (fused and tensor-op reference), forward and
//! forward + backward. Run with `cargo bench --bench spring_forces`.

use burn::tensor::{Device, Tensor, TensorData};
use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use springtime::cloth::{GridSpec, Topology};
use springtime::model::kernels::{HostGraph, cpu};
use springtime::model::{Kernel, SpringNet};

fn state(topo: &Topology, batch: usize) -> (Vec<f32>, Vec<f32>) {
    let rest = topo.rest_positions();
    let x: Vec<f32> = (0..batch)
        .flat_map(|c| {
            rest.iter().enumerate().flat_map(move |(i, p)| {
                let j = (i * 7 + c * 13) as f64;
                [p[0] * 1.02 + 0.01 * j.sin(), p[1] * 0.98, 0.02 * j.cos()].map(|v| v as f32)
            })
        })
        .collect();
    let v: Vec<f32> = (0..x.len())
        .map(|i| ((i as f64) * 0.37).sin() as f32)
        .collect();
    (x, v)
}

fn bench(c: &mut Criterion) {
    let topo = Topology::grid(&GridSpec::default(), 1.0, 1.0);
    let (p, s) = (topo.num_particles(), topo.num_springs());
    let graph = HostGraph::new(&topo.springs, &topo.rest_length, p);
    let k: Vec<f32> = (0..s).map(|i| 10.0 + (i % 90) as f32).collect();
    let b = vec![0.06f32; s];
    let mut group = c.benchmark_group("spring_forces");
    for batch in [1usize, 8, 32] {
        let (x, v) = state(&topo, batch);
        group.throughput(Throughput::Elements(batch as u64));
        let mut out = vec![0f32; x.len()];
        let inputs = cpu::Inputs {
            x: &x,
            v: &v,
            k: &k,
            b: &b,
        };
        group.bench_with_input(BenchmarkId::new("cpu_forward", batch), &batch, |bch, _| {
            bch.iter(|| cpu::forces(&graph, inputs, &mut out))
        });
        let (mut gx, mut gv, mut gk, mut gb) = (
            vec![0f32; x.len()],
            vec![0f32; x.len()],
            vec![0f32; s],
            vec![0f32; s],
        );
        group.bench_with_input(BenchmarkId::new("cpu_backward", batch), &batch, |bch, _| {
            bch.iter(|| {
                let grads = cpu::Grads {
                    x: &mut gx,
                    v: &mut gv,
                    k: &mut gk,
                    b: &mut gb,
                };
                cpu::forces_backward(&graph, inputs, &out, grads)
            })
        });
        let device = Device::flex().autodiff();
        let kk: Vec<f64> = k.iter().map(|&v| v as f64).collect();
        let bb: Vec<f64> = b.iter().map(|&v| v as f64).collect();
        for kernel in [Kernel::Fused, Kernel::Reference] {
            let model = SpringNet::new(&topo, &kk, &bb, &device).with_kernel(kernel);
            let xt = Tensor::<3>::from_data(TensorData::new(x.clone(), [batch, p, 3]), &device);
            let vt = Tensor::<3>::from_data(TensorData::new(v.clone(), [batch, p, 3]), &device);
            group.bench_with_input(
                BenchmarkId::new(format!("burn_{kernel:?}_fwd_bwd"), batch),
                &batch,
                |bch, _| {
                    bch.iter(|| {
                        let f = model.forces(xt.clone(), vt.clone());
                        f.sum().backward()
                    })
                },
            );
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
