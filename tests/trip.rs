//! The inverter's overcurrent trip (`[inverter] i_trip_a`), end to end.

mod common;
use common::*;

#[test]
fn an_overcurrent_trips_the_inverter_latches_its_safe_state_and_is_reported_as_a_fault() {
    // kyslan-pi drives i_q* to its 1.6 A limit on the speed step; a 1.2 A trip level (peak
    // phase current) is crossed during that step.
    let sc = variant(
        "trip",
        "kyslan-pi",
        &[("hold_samples = 3\n", "hold_samples = 3\ni_trip_a = 1.2\n")],
    );
    let r = run("trip", sc.to_str().unwrap(), "lockstep");
    let rows = r.trace();
    const TRIPPED: u32 = 128;
    const SAFE: u32 = 4;
    let first = rows
        .iter()
        .position(|r| r.plant_flags & TRIPPED != 0)
        .expect("the 1.2 A trip level must be crossed on the speed step");
    // Before the trip every phase current (true, no noise in kyslan-pi's currents at the
    // trip's comparator) stayed at or below the level at some sample; from it on the
    // inverter is latched safe to the end of the run although every command arrived.
    assert!(first > 0);
    for r in &rows[first..] {
        assert_eq!(
            r.plant_flags & (TRIPPED | SAFE),
            TRIPPED | SAFE,
            "k = {}",
            r.k
        );
        assert_eq!(r.miss, 0, "k = {}", r.k);
    }
    assert!(rows[..first].iter().all(|r| r.plant_flags & TRIPPED == 0));
    // Reported like a fault, from the first tripped sample, with no recovery.
    let faults = r.summary["faults"].as_array().unwrap();
    assert_eq!(faults.len(), 1, "{faults:?}");
    let f = &faults[0];
    assert!(
        f["fault"].as_str().unwrap().starts_with("overcurrent trip"),
        "{f}"
    );
    assert_eq!(f["injected_k"].as_u64(), Some(rows[first].k));
    assert_eq!(f["speed_recovered_ms"], serde_json::Value::Null);
    assert!(r.stderr.contains("tripped on overcurrent"), "{}", r.stderr);
    // The same scenario without the trip never flags one.
    let plain = run("trip-plain", "kyslan-pi", "lockstep");
    assert!(plain.trace().iter().all(|r| r.plant_flags & TRIPPED == 0));
    assert_eq!(plain.summary["faults"].as_array().map(Vec::len), Some(0));
}
