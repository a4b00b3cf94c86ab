//! Reading never panics, whatever the bytes; malformed input gives a located error.

use proptest::prelude::*;
use so2lin::io::{ReadOptions, read_graph_from};
use so2lin::sim::{SimConfig, simulate};

fn sample_file() -> Vec<u8> {
    let world = simulate(&SimConfig::new(60, 3)).unwrap();
    let mut out = Vec::new();
    so2lin::io::write_g2o(&mut out, &world.graph, None).unwrap();
    out.extend_from_slice(b"EDGE2 0 1 1 0 0.1 1 0 1 1 0 0\nEQUIV 4 5\nLANDMARK 1 2 3\n");
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let _ = read_graph_from(&bytes[..], "random", ReadOptions::default());
    }

    #[test]
    fn random_token_lines_never_panic(
        lines in proptest::collection::vec(
            (prop::sample::select(vec!["EDGE_SE2", "EDGE2", "VERTEX_SE2", "VERTEX2", "EQUIV", "FIX", "#"]),
             proptest::collection::vec(
                prop::sample::select(vec!["0", "1", "-1", "nan", "inf", "-inf", "1e308", "4.9e-324",
                                          "x", "", "18446744073709551616", "3.5", "-0"]), 0..13)),
            0..8)
    ) {
        let text: String = lines.iter().map(|(t, f)| format!("{t} {}\n", f.join(" "))).collect();
        let _ = read_graph_from(text.as_bytes(), "tokens", ReadOptions::default());
    }

    #[test]
    fn truncated_and_mutated_files_never_panic(cut in 0usize..4000, pos in 0usize..4000, byte in any::<u8>()) {
        let mut file = sample_file();
        let cut = cut.min(file.len());
        file.truncate(cut);
        if !file.is_empty() {
            let p = pos % file.len();
            file[p] = byte;
        }
        match read_graph_from(&file[..], "cut.g2o", ReadOptions::default()) {
            Ok(_) => {}
            Err(e) => {
                prop_assert!(e.line >= 1, "error without a line: {e}");
                prop_assert!(e.to_string().starts_with("cut.g2o:"));
            }
        }
    }
}

#[test]
fn bad_information_is_an_error_on_its_line() {
    for info in [
        "nan 0 0 1 0 1",
        "1 0 0 1 0 inf",
        "1 0 0 1 0 -5",
        "-1 0 0 1 0 1",
        "0 0 0 0 0 0",
    ] {
        let text = format!("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 {info}\n");
        let e = read_graph_from(text.as_bytes(), "bad.g2o", ReadOptions::default()).unwrap_err();
        assert_eq!(e.line, 3, "{info}: {e}");
    }
}
