//! The inverter's overcurrent trip (`[inverter] i_trip_a`), end to end.

mod common;
use common::*;

#[test]
fn an_overcurrent_trips_the_inverter_latches_its_safe_state_and_is_reported_as_a_fault() {
    // kyslan-pi's i_d* step to −1.6 A at 20 ms crosses a 1.2 A trip level (peak phase
    // current); its speed step before that does not (i_q* peaks at 0.67 A).
    let sc = variant(
        "trip",
        "kyslan-pi",
        &[("hold_samples = 3\n", "hold_samples = 3\ni_trip_a = 1.2\n")],
    );
    let r = run("trip", sc.to_str().unwrap(), "lockstep");
    let rows = r.trace();
    const TRIPPED: u32 = 128;
    const SAFE: u32 = 4;
    const I_TRIP_A: f64 = 1.2;
    // The trip's comparator: the largest true phase current at t_k, from the row's true
    // i_d, i_q and θ_e (the values the plant compared, bit for bit through the CSV).
    let peak_phase = |x: &drivelab_runtime::trace::TraceRow| {
        let dq = drivelab_control::transforms::Dq { d: x.i_d, q: x.i_q };
        let (a, b, c) = drivelab_control::transforms::inverse_clarke(
            drivelab_control::transforms::inverse_park(dq, x.theta_e),
        );
        a.abs().max(b.abs()).max(c.abs())
    };
    let first = rows
        .iter()
        .position(|r| r.plant_flags & TRIPPED != 0)
        .expect("the 1.2 A trip level must be crossed on the i_d* step");
    assert!(first > 0);
    assert_eq!(rows[first].i_d_ref, -1.6, "k = {}", rows[first].k);
    // Before the trip every phase current stayed at or below the level; at the first
    // tripped sample one is above it: the trip fired on the sample that crossed it, neither
    // early nor late.
    for x in &rows[..first] {
        let i = peak_phase(x);
        assert!(
            i <= I_TRIP_A,
            "k = {}: peak phase current {i} A untripped",
            x.k
        );
    }
    let at_trip = peak_phase(&rows[first]);
    assert!(
        at_trip > I_TRIP_A,
        "k = {}: tripped at {at_trip} A",
        rows[first].k
    );
    // From the trip on the inverter is latched safe to the end of the run although every
    // command arrived.
    for r in &rows[first..] {
        assert_eq!(
            r.plant_flags & (TRIPPED | SAFE),
            TRIPPED | SAFE,
            "k = {}",
            r.k
        );
        assert_eq!(r.miss, 0, "k = {}", r.k);
    }
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
