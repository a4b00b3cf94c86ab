//! Reading speed: parse a simulated 3500-pose g2o file from memory.

use criterion::{Criterion, criterion_group, criterion_main};
use so2lin::io::{ReadOptions, read_graph_from, write_g2o};
use so2lin::sim::{SimConfig, simulate};

fn bench_read(c: &mut Criterion) {
    let world = simulate(&SimConfig::new(3500, 1)).expect("valid simulator config");
    let mut file = Vec::new();
    write_g2o(&mut file, &world.graph, None).expect("writing to memory");
    c.bench_function("read_g2o_sim3500", |b| {
        b.iter(|| {
            read_graph_from(&file[..], "sim", ReadOptions::default()).map(|(g, _)| g.edge_count())
        })
    });
}

criterion_group!(benches, bench_read);
criterion_main!(benches);
