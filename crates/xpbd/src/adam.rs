//! γ fitted by Adam through Burn's autodiff (`fit.optimizer = "adam"`), beside the paper's
//! Levenberg–Marquardt: the same objective — every target's FFT descriptor and clamp reactions
//! against the equilibrium's, and the Poisson penalty — written as a Burn tensor program over
//! the equilibrium op ([`super::op`]), whose backward is the implicit-function adjoint. The
//! parameters are `θ = ln(γ / γ_start)` (positive by construction, one scale for all five),
//! held inside the fit's bounds.

use std::sync::Arc;

use anyhow::{Context, Result, bail};
use burn::module::{Module, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};

use super::descriptor::fft_descriptor_tensor;
use super::lm::Fit;
use super::op::{StaticProblem, static_equilibrium};
use springtime_core::model::springs::to_f64;
use springtime_core::progress::Progress;

/// One target of the Adam fit.
#[derive(Debug, Clone)]
pub struct AdamTarget {
    /// Its scenario, solved from where the fit's equilibria start.
    pub problem: Arc<StaticProblem>,
    /// The target's FFT descriptor.
    pub descriptor: Vec<f64>,
    /// The descriptor residuals' scale.
    pub norm: f64,
    /// The measured reaction magnitudes, one per clamp group, N.
    pub reactions: Vec<f64>,
}

/// The objective's weights and Adam's schedule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamSettings {
    /// Grid vertices per side.
    pub n: usize,
    /// Weight of the reactions' relative errors.
    pub force_weight: f64,
    /// The Poisson penalty's `s_ν`.
    pub poisson_penalty: f64,
    /// Adam steps.
    pub steps: usize,
    /// Learning rate on `θ = ln γ` (a relative step), decaying geometrically to a hundredth of
    /// it over the steps.
    pub lr: f64,
}

#[derive(Module, Debug)]
struct LogGamma {
    theta: Param<Tensor<1>>,
}

fn row(v: &[f64], device: &Device) -> Tensor<1> {
    let v: Vec<f32> = v.iter().map(|&x| x as f32).collect();
    let n = v.len();
    Tensor::from_data(TensorData::new(v, [n]), device)
}

/// `½ Σ r²` of the fit's residuals at γ (a tensor program, differentiable in γ).
pub fn objective(gamma: Tensor<1>, targets: &[AdamTarget], s: &AdamSettings) -> Result<Tensor<1>> {
    let device = gamma.device();
    let mut total = Tensor::<1>::zeros([1], &device);
    for t in targets {
        let (x, reactions) = static_equilibrium(gamma.clone(), &t.problem)?;
        let d = fft_descriptor_tensor(x, s.n, s.n);
        let r = (d - row(&t.descriptor, &device)) / t.norm;
        total = total + r.powi_scalar(2).sum() * 0.5;
        for (g, &target) in t.reactions.iter().enumerate() {
            let mag = reactions
                .clone()
                .slice([g..g + 1, 0..3])
                .powi_scalar(2)
                .sum()
                .sqrt();
            let rel = (mag - target) * (s.force_weight / target.max(1e-300));
            total = total + rel.powi_scalar(2) * 0.5;
        }
    }
    // The Poisson penalty √s_ν · max(0, C01/C11 − 0.5), squared and halved.
    let nu = gamma.clone().narrow(0, 2, 1) / gamma.narrow(0, 1, 1);
    let over = (nu - 0.5).clamp_min(0.0);
    Ok(total + over.powi_scalar(2) * (0.5 * s.poisson_penalty))
}

/// One Adam step on `loss`, then `θ` clamped into `bounds` (the parameter keeps its id, so the
/// optimiser keeps its moments). Refuses a gradient that is not finite (the equilibrium's
/// Hessian singular at this γ).
fn descend(
    optim: &mut ModuleOptimizer,
    module: LogGamma,
    loss: Tensor<1>,
    lr: f64,
    bounds: (&Tensor<1>, &Tensor<1>),
) -> Result<LogGamma> {
    let grads = GradientsParams::from_grads(loss.backward(), &module);
    let finite = grads
        .get(module.theta.id)
        .map(|g: Tensor<1>| g.is_finite().all().into_scalar::<bool>())
        .unwrap_or(false);
    if !finite {
        bail!("the objective's gradient is not finite: the equilibrium's Hessian is singular here");
    }
    let mut module = optim.step(lr, module, grads);
    let (lo, hi) = (bounds.0.clone().inner(), bounds.1.clone().inner());
    module.theta = module
        .theta
        .map(|t| Tensor::from_inner(t.inner().max_pair(lo).min_pair(hi)).require_grad());
    Ok(module)
}

/// Adam from `start` within `[lower, upper]`; the objective after every step in `history`.
pub fn fit(
    targets: &[AdamTarget],
    settings: &AdamSettings,
    start: &[f64],
    lower: &[f64],
    upper: &[f64],
    progress: &Progress,
) -> Result<Fit> {
    let device = Device::flex().autodiff();
    let scale = row(start, &device);
    let bound = |b: &[f64], floor: f64| -> Tensor<1> {
        let v: Vec<f64> = b
            .iter()
            .zip(start)
            .map(|(b, s)| (b / s).max(floor).ln())
            .collect();
        row(&v, &device)
    };
    let (lo, hi) = (bound(lower, 1e-12), bound(upper, 1e-12));
    let mut module = LogGamma {
        theta: Param::from_tensor(Tensor::zeros([start.len()], &device)),
    };
    let mut optim: ModuleOptimizer = AdamConfig::new().init();
    let bar = progress.bar(settings.steps as u64, "adam");
    let mut history = Vec::with_capacity(settings.steps);
    let gamma_of = |m: &LogGamma| m.theta.val().exp() * scale.clone();
    for step in 0..settings.steps {
        let loss = objective(gamma_of(&module), targets, settings)?;
        let value = loss.clone().into_scalar::<f32>() as f64;
        if !value.is_finite() {
            bail!("the Adam fit diverged at step {step} (objective {value})");
        }
        history.push(value);
        let lr = settings.lr * 0.01f64.powf(step as f64 / settings.steps as f64);
        module = descend(&mut optim, module, loss, lr, (&lo, &hi))
            .with_context(|| format!("Adam step {step}"))?;
        bar.set_position(step as u64 + 1);
    }
    bar.finish();
    let gamma = gamma_of(&module).inner();
    let cost = objective(gamma.clone(), targets, settings)?.into_scalar::<f32>() as f64;
    history.push(cost);
    let p = to_f64(gamma);
    Ok(Fit {
        p,
        cost,
        iterations: settings.steps,
        history,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two steps on `c · θ` with `c` = 1, then 0.1: Adam's second update is
    /// `lr · m̂ / (√v̂ + ε)` = 0.7408 lr (moments kept), where a first step from fresh moments
    /// (sign descent) would move by `lr`.
    #[test]
    fn adam_keeps_its_moments_across_steps_and_the_bounds() {
        let device = Device::flex().autodiff();
        let mut module = LogGamma {
            theta: Param::from_tensor(Tensor::zeros([1], &device)),
        };
        let mut optim: ModuleOptimizer = AdamConfig::new().init();
        let (lo, hi) = (row(&[-10.0], &device), row(&[10.0], &device));
        let value = |m: &LogGamma| m.theta.val().into_scalar::<f32>() as f64;
        let lr = 0.1;
        let mut at = vec![value(&module)];
        for c in [1.0, 0.1] {
            let loss = module.theta.val() * c;
            module = descend(&mut optim, module, loss, lr, (&lo, &hi)).unwrap();
            at.push(value(&module));
        }
        assert!((at[0] - at[1] - lr).abs() < 1e-5, "first step {at:?}");
        let (m, v) = (0.9 * 0.1 + 0.1 * 0.1, 0.999 * 0.001 + 0.001 * 0.01);
        let update = lr * (m / (1.0 - 0.81)) / ((v / (1.0 - 0.999f64 * 0.999)).sqrt() + 1e-5);
        assert!(
            (at[1] - at[2] - update).abs() < 1e-4 * update,
            "second step {} vs Adam's {update}",
            at[1] - at[2]
        );
        // The bounds hold.
        let (lo, hi) = (row(&[-10.0], &device), row(&[at[2] as f64 - 1e-3], &device));
        let loss = module.theta.val() * -1.0;
        module = descend(&mut optim, module, loss, lr, (&lo, &hi)).unwrap();
        assert!((value(&module) - (at[2] - 1e-3)).abs() < 1e-6);
    }
}
