//! The core's dependency list is the one the README shows: `cargo tree -e normal
//! --no-default-features --depth 1` names exactly the crates of the README's block, so a new
//! dependency of the core (or a feature left on by default) fails here until it is documented.

use std::collections::BTreeSet;
use std::process::Command;

/// Crate names of the README's `cargo tree` block (the lines after `so2lin v…`).
fn readme_block() -> BTreeSet<String> {
    let readme = include_str!("../README.md");
    let start = readme
        .find("```text\nso2lin v")
        .expect("README has the cargo tree block");
    let block = &readme[start + "```text\n".len()..];
    let block = &block[..block.find("```").expect("the block is closed")];
    block
        .lines()
        .skip(1)
        .filter_map(|l| l.split_whitespace().nth(1).map(str::to_owned))
        .collect()
}

#[test]
fn the_core_depends_on_what_the_readme_shows() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "tree",
            "--offline",
            "-e",
            "normal",
            "--no-default-features",
            "--depth",
            "1",
            "--prefix",
            "none",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let got: BTreeSet<String> = text
        .lines()
        .skip(1)
        .filter_map(|l| l.split_whitespace().next().map(str::to_owned))
        .collect();
    assert_eq!(got, readme_block(), "cargo tree:\n{text}");
}
