//! The GNN's gathers and segment sums (`model::kernels::segment`) against sums written out on
//! the host: values, and the gradients that flow through each into the other (the backward of
//! a segment sum is a gather and vice versa), on every CPU backend and on wgpu (the CubeCL
//! kernel; CI runs it on Mesa's software Vulkan). Some segments are empty, one holds many.

mod common;

use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use springtime::model::kernels::segment::DeviceSegments;
use springtime::model::springs::to_f64;

/// `out[n] = Σ_{owner[e] = n} rows[e]`, written out.
fn host_sum(rows: &[f64], owner: &[i64], segments: usize, width: usize) -> Vec<f64> {
    let mut out = vec![0.0; segments * width];
    for (e, &n) in owner.iter().enumerate() {
        for l in 0..width {
            out[n as usize * width + l] += rows[e * width + l];
        }
    }
    out
}

/// `out[e] = rows[owner[e]]`, written out.
fn host_gather(rows: &[f64], owner: &[i64], width: usize) -> Vec<f64> {
    owner
        .iter()
        .flat_map(|&n| rows[n as usize * width..(n as usize + 1) * width].to_vec())
        .collect()
}

/// Within 1e-5 of the reference's largest magnitude.
fn assert_close(name: &str, a: &[f64], b: &[f64]) {
    common::assert_close(name, a, b, 1e-5);
}

fn check(device: &Device, seed: u64) {
    let mut rng = StdRng::seed_from_u64(seed);
    let (segments, entries, width) = (37, 400, 19);
    // Segments 0..5 stay empty; segment 36 takes a quarter of the entries.
    let owner: Vec<i64> = (0..entries)
        .map(|_| {
            if rng.random_bool(0.25) {
                36
            } else {
                rng.random_range(5..segments as i64)
            }
        })
        .collect();
    let mut random =
        |n: usize| -> Vec<f64> { (0..n).map(|_| rng.random_range(-1.0..1.0)).collect() };
    let (values, x) = (random(entries * width), random(segments * width));
    let (w_sum, w_gather) = (random(segments * width), random(entries * width));

    let ad = device.clone().autodiff();
    let tensor = |v: &[f64], rows: usize| {
        Tensor::<2>::from_data(TensorData::new(v.to_vec(), [rows, width]), &ad)
    };
    let seg = DeviceSegments::new(&owner, segments, &ad);
    let vt = tensor(&values, entries).require_grad();
    let xt = tensor(&x, segments).require_grad();
    let summed = seg.sum(vt.clone());
    let gathered = seg.gather(xt.clone());
    // ℓ = Σ w_sum · sum(values) + Σ w_gather · gather(x): generic upstream gradients.
    let loss = (summed.clone() * tensor(&w_sum, segments)).sum()
        + (gathered.clone() * tensor(&w_gather, entries)).sum();
    let grads = loss.backward();

    assert_close(
        "segment sum",
        &host_sum(&values, &owner, segments, width),
        &to_f64(summed.clone().detach()),
    );
    assert_close(
        "gather",
        &host_gather(&x, &owner, width),
        &to_f64(gathered.detach()),
    );
    assert_close(
        "dℓ/dvalues (a gather)",
        &host_gather(&w_sum, &owner, width),
        &to_f64(vt.grad(&grads).unwrap()),
    );
    assert_close(
        "dℓ/dx (a segment sum)",
        &host_sum(&w_gather, &owner, segments, width),
        &to_f64(xt.grad(&grads).unwrap()),
    );
    // A strided view (the GNN sums slices of concatenated features, and the backward of `cat`
    // hands out slices): the right half of [values | values].
    let wide = Tensor::cat(vec![vt.clone().detach(), vt.clone().detach()], 1);
    let strided = wide.slice([0..entries, width..2 * width]);
    assert_close(
        "segment sum of a strided view",
        &host_sum(&values, &owner, segments, width),
        &to_f64(seg.sum(strided)),
    );
    let empty = to_f64(summed.detach());
    assert!(
        empty[..5 * width].iter().all(|&v| v == 0.0),
        "empty segments sum to zero"
    );
}

#[test]
#[allow(deprecated)]
fn segment_ops_match_host_sums_on_every_backend() {
    for device in [Device::flex(), Device::ndarray()]
        .into_iter()
        .chain(common::wgpu())
    {
        for seed in 0..3 {
            check(&device, seed);
        }
    }
}

/// Out-of-range owners are refused before any kernel indexes with them.
#[test]
#[should_panic(expected = "segment 7 outside 7")]
fn an_owner_outside_the_segments_is_refused() {
    DeviceSegments::new(&[0, 7], 7, &Device::flex());
}
