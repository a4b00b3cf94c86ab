//! Words shared by the commands' reports: rejected edges, what a confidence figure assumes,
//! why a second screening stopped, plurals and fixed decimals.

use clap::ValueEnum;
use so2lin::cycles::BasisKind;
use so2lin::io::InfoOrder;

/// Print rejected edges (at most ten, then a count): one line naming how many and `what`
/// happened to them, then `edge i (from → to): test statistic > threshold`, and what a
/// translation statistic is when one is listed. Nothing when empty.
pub(crate) fn print_rejected(rejected: &[so2lin::batch::RejectedEdge], what: &str) {
    if rejected.is_empty() {
        return;
    }
    println!(
        "{} {what}:",
        plural(rejected.len(), "loop closure", "loop closures")
    );
    for r in rejected.iter().take(10) {
        println!(
            "  edge {} ({} → {}): {} {:.2} > {:.2}",
            r.edge, r.from, r.to, r.test, r.statistic, r.threshold
        );
    }
    if rejected.len() > 10 {
        println!("  … {} more (--json lists all)", rejected.len() - 10);
    }
    if rejected
        .iter()
        .any(|r| r.test == so2lin::online::TRANSLATION_TEST)
    {
        println!(
            "  ({} statistics: the larger of the closure at the chord's two ends, or the first end's alone when it already fails, a lower bound)",
            so2lin::online::TRANSLATION_TEST
        );
    }
}

/// Print the quarantine's noise scales (one line).
pub(crate) fn print_noise_scales(s: &so2lin::online::NoiseScales) {
    println!(
        "noise scales from the accepted cycles (quarantine tests only; the screening keeps the declared noise): angle {:.3} (from {} cycle tests), translation {:.3} (from {})",
        s.angle, s.angle_samples, s.translation, s.translation_samples
    );
}

/// What a success bound or p-value is stated for: "all N edges accepted, none rejected", or
/// "the N accepted edges; R rejected edges left out".
pub(crate) fn accepted_words(accepted: usize, rejected: usize) -> String {
    if rejected == 0 {
        format!("all {accepted} edges accepted, none rejected")
    } else {
        format!(
            "for the {accepted} accepted edges; {} left out",
            plural(rejected, "rejected edge", "rejected edges")
        )
    }
}

/// What the second screening of `r` did, in words (one sentence for every command): `None`
/// when it completed, else why it stopped and that the answer shown is the bootstrapped one.
pub(crate) fn second_screening_words(
    r: &so2lin::batch::BatchResult,
    joint_level: f64,
) -> Option<String> {
    use so2lin::screening::{Limit, SecondOutcome};
    const SHOWING: &str = "showing the bootstrapped answer, not a screened set";
    match r.outcome {
        SecondOutcome::Complete => None,
        SecondOutcome::TooMany(t) => Some(match t.limit {
            Limit::Hypotheses => format!(
                "second screening stopped: too many hypotheses ({} ≥ cap {}); {SHOWING}",
                t.found, t.cap
            ),
            Limit::Visits => format!(
                "second screening stopped: its search budget of {} partial vectors was exhausted with {} found; {SHOWING}",
                t.visited, t.found
            ),
            Limit::Memory => format!(
                "second screening stopped: the memory bound of {} MiB was reached with {} found; {SHOWING}",
                so2lin::screening::MAX_ENUMERATION_BYTES >> 20,
                t.found
            ),
        }),
        SecondOutcome::NoneInside => Some(format!(
            "second screening: no candidate vector of the {} ambiguous cycles passes the joint χ² test at level {} (the measurements disagree with their declared noise, or hold an outlier); {SHOWING}",
            r.ambiguous.len(),
            joint_level
        )),
    }
}

/// "1 hypothesis", "3 hypotheses".
pub(crate) fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// A number with `digits` decimals, never "-0.00…".
pub(crate) fn fixed(x: f64, digits: usize) -> String {
    let s = format!("{x:.digits$}");
    match s.strip_prefix('-') {
        Some(rest) if rest.bytes().all(|b| b == b'0' || b == b'.') => rest.to_owned(),
        _ => s,
    }
}

/// The information order as a user writes it.
pub(crate) fn order_name(order: InfoOrder) -> &'static str {
    match order {
        InfoOrder::Auto => "auto",
        InfoOrder::G2o => "g2o",
        InfoOrder::Toro => "TORO",
    }
}

/// A basis as its `--basis` value.
pub(crate) fn basis_name(kind: BasisKind) -> String {
    kind.to_possible_value()
        .map_or_else(|| format!("{kind:?}"), |v| v.get_name().to_owned())
}
