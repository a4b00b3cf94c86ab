//! The command-line tool on hostile or misleading input: closed pipes, full disks, endless
//! lines, directories, logs given as graphs, absurd numbers and settings, files without a 2D
//! edge. Every case ends with a one-line error (or quietly), never a panic (status 101).

use std::path::PathBuf;
use std::process::{Command, Output, Stdio};

fn so2lin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_so2lin"))
}

fn scratch_file(name: &str, content: &[u8]) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli_hostile");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, content).unwrap();
    path
}

/// A small valid graph (a simulated world).
fn graph_text() -> Vec<u8> {
    let world = so2lin::sim::simulate(&so2lin::sim::SimConfig::new(80, 4)).unwrap();
    let mut out = Vec::new();
    so2lin::io::write_g2o(&mut out, &world.graph, None).unwrap();
    out
}

/// The command failed with exit status 1 and exactly one line on stderr containing `want`.
fn assert_one_line_error(out: &Output, want: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.starts_with("error: ") && err.contains(want), "{err}");
}

#[test]
fn a_closed_pipe_exits_quietly_and_a_full_disk_with_one_line() {
    let graph = scratch_file("pipe.g2o", &graph_text());
    let g = graph.to_str().unwrap();
    let commands: [&[&str]; 6] = [
        &["info", g],
        &["screen", g],
        &["solve", g],
        &["stream", g],
        &["bases", g],
        &["demo", "--poses", "60"],
    ];
    for args in commands {
        // A pipe whose reading end is already closed: the first write fails with EPIPE.
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let out = so2lin()
            .args(args)
            .stdout(writer)
            .stderr(Stdio::piped())
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(141), "{args:?}: {out:?}");
        assert!(out.stderr.is_empty(), "{args:?}: {out:?}");
        if cfg!(target_os = "linux") {
            let full = std::fs::OpenOptions::new()
                .write(true)
                .open("/dev/full")
                .unwrap();
            let out = so2lin().args(args).stdout(full).output().unwrap();
            assert_one_line_error(&out, "No space left on device");
        }
    }
}

#[test]
fn endless_lines_directories_and_logs_are_named_errors() {
    let mut long = b"VERTEX_SE2 0 0 0 0\n".to_vec();
    long.extend(std::iter::repeat_n(b'1', so2lin::io::MAX_LINE_BYTES + 10));
    let long = scratch_file("long.g2o", &long);
    let out = so2lin().arg("info").arg(&long).output().unwrap();
    assert_one_line_error(&out, "long.g2o:2: line is longer than 1048576 bytes");
    if cfg!(target_os = "linux") {
        let out = so2lin().args(["info", "/dev/zero"]).output().unwrap();
        assert_one_line_error(&out, "/dev/zero:1: line is longer");
    }
    let dir = long.parent().unwrap();
    let out = so2lin().arg("screen").arg(dir).output().unwrap();
    assert_one_line_error(&out, "is a directory");
    // A log written by the demo, given to a graph command.
    let log = dir.join("given.mcap");
    let demo = so2lin()
        .args(["demo", "--poses", "60", "--log"])
        .arg(&log)
        .output()
        .unwrap();
    assert!(demo.status.success());
    let out = so2lin().arg("solve").arg(&log).output().unwrap();
    assert_one_line_error(&out, "this is an MCAP log, not a graph file");
    assert!(String::from_utf8_lossy(&out.stderr).contains("so2lin replay"));
}

#[test]
fn a_corrupt_log_is_reported_as_corruption() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cli_hostile");
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("corrupt.mcap");
    let demo = so2lin()
        .args(["demo", "--poses", "300", "--log"])
        .arg(&log)
        .output()
        .unwrap();
    assert!(demo.status.success());
    let mut bytes = std::fs::read(&log).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x20;
    std::fs::write(&log, &bytes).unwrap();
    let out = so2lin()
        .args(["replay", "--verify"])
        .arg(&log)
        .output()
        .unwrap();
    assert_one_line_error(&out, "corrupt log near byte");
    assert!(!String::from_utf8_lossy(&out.stdout).contains("verified"));
}

#[test]
fn absurd_numbers_and_settings_are_rejected_with_their_place() {
    let mut text = graph_text();
    text.extend_from_slice(b"EDGE_SE2 3 40 1 0 1e300 1 0 0 1 0 1\n");
    let lines = text.iter().filter(|&&b| b == b'\n').count();
    let huge = scratch_file("huge_angle.g2o", &text);
    let out = so2lin().arg("screen").arg(&huge).output().unwrap();
    assert_one_line_error(
        &out,
        &format!("huge_angle.g2o:{lines}: edge 3→40: dθ = 1e300 rad is beyond"),
    );
    let graph = scratch_file("settings.g2o", &graph_text());
    for (alpha, want) in [("-1", "must be in (0, 1)"), ("1e-17", "too small")] {
        let out = so2lin()
            .arg("screen")
            .arg(&graph)
            .args(["--alpha", alpha])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{err}");
        assert!(err.contains("invalid value") && err.contains(want), "{err}");
    }
}

#[test]
fn extreme_information_names_the_edges() {
    // Angle information 1e20 on one edge beside information ~30 on the others.
    let text = String::from_utf8(graph_text()).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let first_edge = lines
        .iter()
        .position(|l| l.starts_with("EDGE_SE2"))
        .unwrap();
    let k = first_edge + 5;
    let mut fields: Vec<&str> = lines[k].split(' ').collect();
    fields[11] = "1e20";
    lines[k] = fields.join(" ");
    let file = scratch_file("extreme.g2o", (lines.join("\n") + "\n").as_bytes());
    for cmd in ["screen", "solve"] {
        let out = so2lin().arg(cmd).arg(&file).output().unwrap();
        if out.status.success() {
            continue; // solved: acceptable
        }
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("NonPositivePivot"), "{err}");
        assert_one_line_error(&out, &format!("edge 5 (line {})", k + 1));
        assert!(err.contains("angle information 1e20"), "{err}");
    }
}

#[test]
fn files_without_a_2d_edge_fail_and_skipped_lines_are_reported() {
    let se3 = scratch_file(
        "se3.g2o",
        b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1\n",
    );
    for cmd in ["info", "screen", "solve", "bases"] {
        let out = so2lin().arg(cmd).arg(&se3).output().unwrap();
        assert_one_line_error(&out, "no 2D pose edge");
        assert!(String::from_utf8_lossy(&out.stderr).contains("EDGE_SE3:QUAT ×1"));
    }
    let out = so2lin()
        .args(["plot", "--out"])
        .arg(se3.with_extension("svg"))
        .arg(&se3)
        .output()
        .unwrap();
    assert_one_line_error(&out, "no 2D pose edge");
    let mut text = graph_text();
    text.extend_from_slice(b"LANDMARK 1 2\nLANDMARK 3 4\n");
    let mixed = scratch_file("mixed.g2o", &text);
    let out = so2lin().arg("screen").arg(&mixed).output().unwrap();
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("skipped 2 lines with other tags: LANDMARK ×2"),
        "{err}"
    );
}

#[test]
fn output_uses_human_words_and_help_shows_defaults() {
    let graph = scratch_file("words.g2o", &graph_text());
    let info = so2lin().arg("info").arg(&graph).output().unwrap();
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(text.contains("information order     g2o"), "{text}");
    let screen = so2lin().arg("screen").arg(&graph).output().unwrap();
    let text = String::from_utf8_lossy(&screen.stdout);
    assert!(text.contains("basis incremental"), "{text}");
    assert!(
        !text.contains("1 hypotheses") && !text.contains("-0.00"),
        "{text}"
    );
    let out = so2lin()
        .args(["demo", "--poses", "60", "--seed", "3"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("incremental basis"), "{text}");
    assert!(text.contains("so2lin-demo-60-3.mcap"), "{text}");
    assert!(text.contains("so2lin-demo-60-3.svg"), "{text}");
    let help = so2lin().args(["screen", "--help"]).output().unwrap();
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(text.contains("[default: 0.01"), "{text}");
    assert!(text.contains("[default: 1; 3 with --paper]"), "{text}");
}
