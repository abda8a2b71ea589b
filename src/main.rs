use clap::Parser;

// Large tensors are allocated and freed every step; mimalloc reuses that memory instead of
// returning it to the kernel and faulting fresh zeroed pages back in (measured: about a
// quarter of a training step went to page clearing with the system allocator).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

// mimalloc's option setter (in the C library that `mimalloc` links; `libmimalloc-sys` declares
// it only under a feature that needs another crate).
unsafe extern "C" {
    fn mi_option_set(option: std::ffi::c_int, value: std::ffi::c_long);
}

/// `mi_option_purge_delay` (15 in `mi_option_e` of mimalloc v3, which `libmimalloc-sys` 0.1.49
/// builds, and of v2).
const MI_OPTION_PURGE_DELAY: std::ffi::c_int = 15;

/// Keeps freed memory in the process instead of returning it to the kernel after mimalloc's
/// default delay (1 s in v3; a delay of 1 s measured no faster): the baselines free and reallocate tensors of ~100 MB every step (the GNN's
/// edge features at Table 2's size), each time faulting in zeroed pages again. Measured on
/// two cores, a Table 2 GNN iteration on flex: 8.9 s → 5.4 s, peak RSS 4.63 → 4.72 GB.
/// `MIMALLOC_PURGE_DELAY` in the environment still decides where it is set.
fn keep_freed_memory() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: a plain C call with an option index and a value, before any thread starts.
        unsafe { mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
    }
}

fn main() -> std::process::ExitCode {
    keep_freed_memory();
    match springtime::cli::run(springtime::cli::Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
