//! Run-time choice of the Burn device: one model, three backends.

use std::fmt;
use std::str::FromStr;

use burn::tensor::Device;
use serde::{Deserialize, Serialize};

/// The compute backend a job runs on (config key `backend`, CLI `--backend`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// Burn's pure-Rust CPU backend: the default and the fastest on CPU.
    #[default]
    Flex,
    /// Burn's ndarray CPU backend (deprecated upstream; kept for parity tests).
    Ndarray,
    /// Burn's wgpu backend (GPU, or a software Vulkan device); needs the `wgpu` feature.
    Wgpu,
}

impl Backend {
    /// Every backend name, for error messages.
    pub const NAMES: &'static str = "flex, ndarray, wgpu";

    /// The plain (no-autodiff) device of this backend.
    ///
    /// Fails for `wgpu` when the binary was built without the `wgpu` feature.
    pub fn device(self) -> anyhow::Result<Device> {
        match self {
            Backend::Flex => Ok(Device::flex()),
            #[allow(deprecated)]
            Backend::Ndarray => Ok(Device::ndarray()),
            #[cfg(feature = "wgpu")]
            Backend::Wgpu => Ok(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)),
            #[cfg(not(feature = "wgpu"))]
            Backend::Wgpu => anyhow::bail!(
                "backend `wgpu` is not compiled in: this build used `--no-default-features`; rebuild without it"
            ),
        }
    }

    /// The name used in configs and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Flex => "flex",
            Backend::Ndarray => "ndarray",
            Backend::Wgpu => "wgpu",
        }
    }
}

/// The float type a process simulates in (`springtime eval --precision`).
///
/// Burn fixes a device's float type when the first tensor is made on it, for the whole
/// process: so f64 is chosen once, before anything else runs (a `springtime eval` of its own),
/// and training always runs in f32.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// The backends' default.
    #[default]
    F32,
    /// Double precision on the CPU backends (`flex`, `ndarray`): a rollout's own rounding far
    /// below f32's, for long chaotic horizons.
    F64,
}

impl Precision {
    /// Makes `F64` the float type of the CPU backends' devices in this process; fails once a
    /// tensor exists on them.
    pub fn apply(self) -> anyhow::Result<()> {
        if self == Precision::F64 {
            #[allow(deprecated)]
            for mut device in [Device::flex(), Device::ndarray()] {
                device
                    .configure(burn::tensor::FloatDType::F64)
                    .map_err(|e| {
                        anyhow::anyhow!(
                            "precision f64: {e:?} (the device already holds f32 tensors in this \
                             process; evaluate in a process of its own, `springtime eval RUN \
                             --precision f64`)"
                        )
                    })?;
            }
        }
        Ok(())
    }

    /// The float type tensors made on `device` get: `"f64"` or `"f32"` (any other type is
    /// reported as its name).
    pub fn of(device: &Device) -> String {
        match device.settings().float_dtype {
            burn::tensor::FloatDType::F64 => "f64".into(),
            burn::tensor::FloatDType::F32 => "f32".into(),
            other => format!("{other:?}").to_lowercase(),
        }
    }
}

/// What `device` is, for reports: `cpu (flex)`, `cpu (ndarray)`, or for a CubeCL device the
/// runtime and the adapter's own name (e.g. `cubecl wgpu: NVIDIA H100 80GB HBM3`).
pub fn describe(device: &Device) -> String {
    use burn::backend::DispatchDevice;
    match device.clone().inner().as_dispatch() {
        DispatchDevice::Flex(_) => "cpu (flex)".to_string(),
        DispatchDevice::NdArray(_) => "cpu (ndarray)".to_string(),
        #[cfg(feature = "wgpu")]
        DispatchDevice::Cube(d) => {
            let client = d.client();
            format!(
                "cubecl {}: {}",
                client.name(),
                client.properties().identity.name
            )
        }
        #[allow(unreachable_patterns)]
        other => format!("{other:?}"),
    }
}

/// The largest single buffer `device` can allocate, bytes: on a CubeCL device the runtime's
/// page limit (wgpu: the smaller of the adapter's largest buffer and largest storage binding;
/// 128 MiB on Mesa's lavapipe); `None` on the CPU backends, which have no such limit.
pub fn max_buffer_bytes(device: &Device) -> Option<u64> {
    use burn::backend::DispatchDevice;
    match device.clone().inner().as_dispatch() {
        #[cfg(feature = "wgpu")]
        DispatchDevice::Cube(d) => Some(d.client().properties().memory.max_page_size),
        _ => None,
    }
}

/// Whether `device` computes on the host CPU (flex, ndarray) rather than through a GPU runtime.
pub fn is_host(device: &Device) -> bool {
    max_buffer_bytes(device).is_none()
}

impl fmt::Display for Backend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Backend {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "flex" => Ok(Backend::Flex),
            "ndarray" => Ok(Backend::Ndarray),
            "wgpu" => Ok(Backend::Wgpu),
            other => Err(format!(
                "unknown backend `{other}` (expected one of: {})",
                Backend::NAMES
            )),
        }
    }
}
