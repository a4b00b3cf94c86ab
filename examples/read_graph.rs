//! Read a g2o / TORO file (or simulate a world when no file is given) and print its
//! summary, then stream its edges one at a time as the online estimator consumes them.
//!
//! ```text
//! cargo run --release --example read_graph -- ../shared/datasets/M3500a.g2o
//! ```

use so2lin::io::{InfoOrder, ReadOptions, Reader, read_graph};
use so2lin::sim::{SimConfig, simulate};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let Some(path) = std::env::args().nth(1) else {
        let world = simulate(&SimConfig::new(500, 7))?;
        println!("simulated: {:?}", world.graph.stats());
        return Ok(());
    };
    let (graph, summary) = read_graph(&path, ReadOptions::default())?;
    println!("{path}: {:?}", graph.stats());
    println!(
        "information order {:?}, skipped {:?}",
        summary.order, summary.skipped
    );

    // Streaming: edges in file order, one at a time.
    let mut reader = Reader::open(&path, InfoOrder::Auto)?;
    let mut loops = 0;
    for edge in reader.edges() {
        let edge = edge?;
        if !edge.is_odometric() {
            loops += 1;
        }
    }
    println!("streamed {loops} loop closures");
    Ok(())
}
