//! The command-line tool: simulate is deterministic, info reports, bad input fails cleanly.

use std::path::PathBuf;
use std::process::Command;

fn so2lin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_so2lin"))
}

fn scratch(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli");
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn simulate_same_seed_is_byte_identical() {
    let (a, b) = (scratch("a.g2o"), scratch("b.g2o"));
    for out in [&a, &b] {
        let st = so2lin()
            .args(["simulate", "--poses", "500", "--seed", "9", "--out"])
            .arg(out)
            .status()
            .unwrap();
        assert!(st.success());
    }
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let ta = std::fs::read(a.with_extension("truth.json")).unwrap();
    assert_eq!(ta, std::fs::read(b.with_extension("truth.json")).unwrap());
    let truth: serde_json::Value = serde_json::from_slice(&ta).unwrap();
    assert_eq!(truth["truth"]["poses"].as_array().unwrap().len(), 500);

    let out = so2lin().arg("info").arg(&a).arg("--json").output().unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["nodes"], 500);
    assert_eq!(v["components"], 1);
    let (m, n) = (v["edges"].as_u64().unwrap(), v["nodes"].as_u64().unwrap());
    assert_eq!(v["cycles"].as_u64().unwrap(), m - n + 1);
    assert_eq!(v["odometric_edges"], 499);
    for key in ["loop_closures", "parallel_edges", "skipped", "sigma_theta"] {
        assert!(v.get(key).is_some(), "missing {key}");
    }
}

#[test]
fn bad_input_exits_nonzero_with_one_line() {
    let bad = scratch("bad.g2o");
    std::fs::write(
        &bad,
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 zz 1 0 0 1 0 1\n",
    )
    .unwrap();
    let out = so2lin().arg("info").arg(&bad).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(
        err.contains("bad.g2o:2:") && err.contains("dtheta"),
        "{err}"
    );
    let out = so2lin()
        .args(["info", "/nonexistent/file.g2o"])
        .output()
        .unwrap();
    assert!(!out.status.success());
}

#[test]
fn demo_runs() {
    let out = so2lin().args(["demo", "--poses", "300"]).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("nodes") && text.contains("300"), "{text}");
}
