use clap::Parser;

// Large tensors are allocated and freed every step; mimalloc reuses that memory instead of
// returning it to the kernel and faulting fresh zeroed pages back in (measured: about a
// quarter of a training step went to page clearing with the system allocator).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    match springtime::cli::run(springtime::cli::Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
