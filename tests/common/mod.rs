//! Shared helpers for integration tests: locating the benchmark datasets.
#![allow(dead_code)]

use std::path::PathBuf;

/// The datasets folder: `$SO2LIN_DATASETS`, else `../shared/datasets` beside the repository.
///
/// Returns `None` (after printing why) when it is absent, so tests skip on a user's machine;
/// panics instead when `SO2LIN_REQUIRE_DATASETS=1` (set by `.ci/run`).
pub fn datasets_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("SO2LIN_DATASETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR"))
                .join("..")
                .join("shared")
                .join("datasets")
        });
    if dir.is_dir() {
        return Some(dir);
    }
    let required = std::env::var("SO2LIN_REQUIRE_DATASETS").is_ok_and(|v| v == "1");
    assert!(
        !required,
        "SO2LIN_REQUIRE_DATASETS=1 but {} is not a directory",
        dir.display()
    );
    eprintln!(
        "skipping: benchmark datasets not found at {} (set SO2LIN_DATASETS)",
        dir.display()
    );
    None
}

/// A dataset file, or `None` (skip) as for [`datasets_dir`]; a missing file in a present
/// folder is a failure when datasets are required.
pub fn dataset(name: &str) -> Option<PathBuf> {
    let path = datasets_dir()?.join(name);
    if path.is_file() {
        return Some(path);
    }
    let required = std::env::var("SO2LIN_REQUIRE_DATASETS").is_ok_and(|v| v == "1");
    assert!(
        !required,
        "SO2LIN_REQUIRE_DATASETS=1 but {} is missing",
        path.display()
    );
    eprintln!("skipping: {} not found", path.display());
    None
}

/// The names of the files in the datasets folder (its `.md` notes left out), sorted; `None`
/// (skip) as for [`datasets_dir`].
pub fn dataset_names() -> Option<(PathBuf, Vec<String>)> {
    let dir = datasets_dir()?;
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| !n.ends_with(".md"))
        .collect();
    names.sort();
    Some((dir, names))
}
