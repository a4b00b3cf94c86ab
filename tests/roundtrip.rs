//! g2o written by the writer reads back to identical edges.

use proptest::prelude::*;
use so2lin::io::{ReadOptions, read_graph_from, write_g2o};
use so2lin::sim::{SimConfig, simulate};

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn writer_round_trip(poses in 2usize..300, seed in any::<u64>(),
                         sigma_theta in 0.001f64..1.0, sigma_xy in 0.001f64..1.0) {
        let mut c = SimConfig::new(poses, seed);
        c.sigma_theta = sigma_theta;
        c.sigma_xy = sigma_xy;
        let world = simulate(&c).unwrap();
        let mut out = Vec::new();
        write_g2o(&mut out, &world.graph, None).unwrap();
        let (back, _) = read_graph_from(&out[..], "rt", ReadOptions::default()).unwrap();
        prop_assert_eq!(world.graph.edges(), back.edges());
        prop_assert_eq!(world.graph.nodes(), back.nodes());
    }
}
