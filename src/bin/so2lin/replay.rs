//! `so2lin replay`: rebuild a run from its MCAP log; verify it step by step, or time it.

use std::path::Path;

use serde_json::json;

use so2lin::log::{read_log, replay};

use crate::stream::Latency;

pub fn run(path: &Path, verify: bool, as_json: bool) -> Result<(), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let log = read_log(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    let r = replay(&log, verify).map_err(|e| format!("{}: {e}", path.display()))?;
    let lat = Latency::of(r.latency_ns.clone());
    if as_json {
        let v = json!({
            "file": path.display().to_string(),
            "steps": r.steps,
            "recorded_steps": log.steps.len(),
            "truncated": r.truncated,
            "verified": verify && r.divergence.is_none(),
            "divergence": r.divergence.as_ref().map(|d| json!({"step": d.step, "channel": d.channel, "recorded": d.recorded, "replayed": d.replayed})),
            "maintenance_records": log.maintenance.len(),
            "latency_us": lat,
            "source": log.metadata.get("source"),
        });
        println!("{v}");
    } else {
        println!(
            "{}: {} steps recorded (source {})",
            path.display(),
            log.steps.len(),
            log.metadata.get("source").map_or("?", |s| s.as_str())
        );
        if let Some(why) = &r.truncated {
            println!(
                "the log was cut ({why}); it held {} complete steps",
                log.steps.len()
            );
        }
        if verify && r.divergence.is_none() {
            let done = log.maintenance.len();
            let between = if done > 0 {
                format!(
                    ", and what the maintenance between steps did, {}",
                    crate::report::plural(done, "time", "times")
                )
            } else {
                String::new()
            };
            println!(
                "verified: all {} steps identical to the recording (outcomes, newest poses, snapshots{between})",
                r.steps
            );
        }
        println!(
            "replay latency per add_edge (µs): p50 {:.2}, p90 {:.2}, p99 {:.2}, max {:.2}, mean {:.2}",
            lat.p50, lat.p90, lat.p99, lat.max, lat.mean
        );
    }
    if let Some(d) = r.divergence {
        return Err(format!(
            "divergence at step {} on {}: recorded {} but replay gave {}",
            d.step, d.channel, d.recorded, d.replayed
        ));
    }
    Ok(())
}
