//! Choosing the Burn backend at run time.
//!
//! Burn 0.22 carries the backend in the `Device`, so a backend is a value,
//! not a type: the training code is the same for all of them. The device is
//! always chosen explicitly, because `Device::default()` prefers GPU backends
//! in a fixed order even on a machine without a GPU.

use anyhow::Result;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

/// A Burn backend the trainer and baker can run on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// Burn's NdArray CPU backend (deprecated upstream, kept for the tests).
    Ndarray,
    /// Burn's Flex CPU backend (pure Rust); measured faster than NdArray for
    /// this model on 2 cores (see the crate README), hence the default.
    #[default]
    Flex,
    /// Burn's wgpu backend (a GPU through Vulkan/Metal/DX12); needs this
    /// crate built with the `wgpu` cargo feature.
    Wgpu,
}

impl std::fmt::Display for BackendKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Ndarray => "ndarray",
            Self::Flex => "flex",
            Self::Wgpu => "wgpu",
        })
    }
}

impl BackendKind {
    /// The inference device (no autodiff) of this backend.
    pub fn device(self) -> Result<Device> {
        match self {
            #[allow(deprecated)]
            Self::Ndarray => Ok(Device::ndarray()),
            Self::Flex => Ok(Device::flex()),
            Self::Wgpu => wgpu_device(),
        }
    }

    /// Whether results are reproducible bit for bit on this backend (CPU
    /// backends are; on a GPU, parallel reductions sum in no fixed order and
    /// Burn's wgpu seeding is per device).
    pub fn is_deterministic(self) -> bool {
        !matches!(self, Self::Wgpu)
    }
}

#[cfg(feature = "wgpu")]
fn wgpu_device() -> Result<Device> {
    Ok(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice))
}

#[cfg(not(feature = "wgpu"))]
fn wgpu_device() -> Result<Device> {
    anyhow::bail!(
        "this nppp was built without the `wgpu` cargo feature; rebuild with \
         `--features nppp-nn/wgpu` or choose another backend (nppp render: --decoder burn-flex|burn-ndarray|cpu; nppp train/bake: --backend flex|ndarray)"
    )
}

/// Keeps `matrixmultiply`'s products on the calling thread (sets
/// `MATMUL_NUM_THREADS=1` unless the user set it). The renderer already
/// runs one wavefront per core, and each wavefront's decoder batch is a
/// `matrixmultiply` product; Burn's ndarray backend turns on that crate's
/// own threading, which would split every batch over extra threads that
/// spin (`sched_yield`) on the cores the renderer is using: 13% of a P = 0
/// room-skylight render went to yielding, and samples/s rose 1.2x without
/// it (measured on 2 cores). `nppp render` and `nppp bench` call it, and so
/// does the decoder throughput example, whose "one thread" would otherwise
/// mean every core on large batches.
///
/// # Safety
/// It writes the process environment: call it before any other thread
/// exists (first thing in `main`), so that nothing reads the environment
/// concurrently.
pub unsafe fn single_threaded_gemm() {
    if std::env::var_os("MATMUL_NUM_THREADS").is_none() {
        // SAFETY: the caller guarantees that no other thread exists.
        unsafe { std::env::set_var("MATMUL_NUM_THREADS", "1") };
    }
}
