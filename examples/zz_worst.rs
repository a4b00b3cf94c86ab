use so2lin::io::{InfoOrder, Reader};
use so2lin::online::{OnlineConfig, OnlineEstimator, robot_order};
use std::time::Instant;
fn main() {
    let path = std::env::args().nth(1).unwrap();
    let newest = std::env::args().nth(2).as_deref() != Some("none");
    let mut r = Reader::open(&path, InfoOrder::Auto).unwrap();
    let edges: Vec<_> = r.edges().collect::<Result<Vec<_>, _>>().unwrap();
    let edges = robot_order(&edges);
    let mut est = OnlineEstimator::new(OnlineConfig::default()).unwrap();
    let mut rows = Vec::new();
    for (i, e) in edges.iter().enumerate() {
        let c0 = est.counters().clone();
        let t0 = Instant::now();
        let s = est.add_edge(*e).unwrap();
        if newest { std::hint::black_box(est.newest().unwrap()); }
        let dt = t0.elapsed().as_secs_f64() * 1e6;
        let c1 = est.counters();
        rows.push((dt, i, format!("{:?} reord+{} ren+{} waits+{} resc+{} cyc={} det={} amb={}", s.kind, c1.reorders - c0.reorders, c1.estimate_renewals - c0.estimate_renewals, c1.renewal_waits - c0.renewal_waits, c1.rescreens - c0.rescreens, c1.cycles, c1.determined, c1.ambiguous)));
    }
    rows.sort_by(|a, b| b.0.total_cmp(&a.0));
    for (dt, i, s) in rows.iter().take(12) { println!("{dt:9.0}us step {i}: {}", &s[..s.len().min(200)]); }
}
