//! Shared helpers for integration tests: locating the benchmark datasets.
#![allow(dead_code)]

use std::io::{Cursor, Seek, SeekFrom, Write};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

/// An in-memory log sink whose bytes a test can read while a recorder still owns a clone.
#[derive(Clone, Default)]
pub struct SharedSink(Arc<Mutex<Cursor<Vec<u8>>>>);

impl Write for SharedSink {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for SharedSink {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.0.lock().unwrap().seek(pos)
    }
}

impl SharedSink {
    /// Bytes written so far.
    pub fn len(&self) -> usize {
        self.0.lock().unwrap().get_ref().len()
    }
    /// A copy of the bytes written so far.
    pub fn bytes(&self) -> Vec<u8> {
        self.0.lock().unwrap().get_ref().clone()
    }
}

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

/// Every edge of a graph file, in the file's order (test data: a bad file fails the test).
pub fn edges_of(path: &std::path::Path) -> Vec<so2lin::graph::Edge> {
    so2lin::io::Reader::open(path, so2lin::io::InfoOrder::Auto)
        .unwrap()
        .edges()
        .map(|e| e.unwrap())
        .collect()
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

/// Edge `e` with `turns` whole turns (2π each) added to its angle measurement.
pub fn turned(e: &so2lin::graph::Edge, turns: i32) -> so2lin::graph::Edge {
    let m = e.measurement();
    let m = so2lin::graph::Pose2::new(m.x, m.y, m.theta + std::f64::consts::TAU * f64::from(turns));
    so2lin::graph::Edge::new(e.from(), e.to(), m, e.information()).unwrap()
}

/// Edge `e` written the other way: ends swapped, the inverse measurement, the information of
/// the same noise seen from the other end ([`so2lin::graph::Edge::reversed`]).
pub fn reversed(e: &so2lin::graph::Edge) -> so2lin::graph::Edge {
    e.reversed()
}
