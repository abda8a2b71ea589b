//! File formats of other tools, read and written without policy (what a file means for a run
//! is decided by the modules above: `import`, `export`, `sim::contact`).

pub mod obj;
