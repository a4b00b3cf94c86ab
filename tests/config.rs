//! The public configuration types deserialise: round trips through JSON, and (where a type
//! has defaults) fields left out take them.

use serde::Serialize;
use serde::de::DeserializeOwned;

use so2lin::batch::BatchConfig;
use so2lin::cycles::BasisKind;
use so2lin::online::OnlineConfig;
use so2lin::refine::RefineConfig;
use so2lin::screening::ScreeningConfig;
use so2lin::sim::SimConfig;

fn round_trip<T: Serialize + DeserializeOwned + PartialEq + std::fmt::Debug>(value: T) {
    let text = serde_json::to_string(&value).unwrap();
    let back: T = serde_json::from_str(&text).unwrap();
    assert_eq!(back, value, "{text}");
}

fn screening() -> ScreeningConfig {
    ScreeningConfig {
        alpha: 0.001,
        max_hypotheses: 7,
        ..ScreeningConfig::default()
    }
}

#[test]
fn configs_round_trip_through_json() {
    round_trip(OnlineConfig {
        screening: screening(),
        quarantine: false,
        evict: true,
        estimate_every_step: false,
        renewal_delay: 0.25,
    });
    round_trip(BatchConfig {
        basis: BasisKind::Mcb,
        screening: screening(),
    });
    round_trip(SimConfig {
        sigma_theta: 0.2,
        ..SimConfig::new(123, 9)
    });
    round_trip(RefineConfig {
        initial_damping: 1e-3,
        ..RefineConfig::with_iterations(17)
    });
}

#[test]
fn fields_left_out_take_the_defaults() {
    let r: RefineConfig = serde_json::from_str(r#"{"iterations": 7}"#).unwrap();
    assert_eq!(r, RefineConfig::with_iterations(7));
    let b: BatchConfig = serde_json::from_str(r#"{"basis": "mcb"}"#).unwrap();
    assert_eq!(
        b,
        BatchConfig {
            basis: BasisKind::Mcb,
            ..BatchConfig::default()
        }
    );
    let o: OnlineConfig = serde_json::from_str("{}").unwrap();
    assert_eq!(o, OnlineConfig::default());
    // The simulator has no defaults without a size and seed: every field is required.
    assert!(serde_json::from_str::<SimConfig>(r#"{"poses": 10}"#).is_err());
}
