//! Marks a build without the benchmark datasets: when `$SO2LIN_DATASETS` (default
//! `../shared/datasets` beside the repository) is not a directory, the cfg `so2lin_no_datasets`
//! is set, and the tests that need the datasets are compiled as `#[ignore]`d, so
//! `cargo test` counts them as ignored instead of passing them silently.

use std::path::PathBuf;

fn main() {
    println!("cargo::rustc-check-cfg=cfg(so2lin_no_datasets)");
    println!("cargo::rerun-if-env-changed=SO2LIN_DATASETS");
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let dir = std::env::var_os("SO2LIN_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| manifest.join("..").join("shared").join("datasets"));
    // Watch the folder, or the nearest existing ancestor for it to appear.
    let watched = dir.ancestors().find(|p| p.is_dir()).unwrap_or(&manifest);
    println!("cargo::rerun-if-changed={}", watched.display());
    if !dir.is_dir() {
        println!("cargo::rustc-cfg=so2lin_no_datasets");
    }
}
