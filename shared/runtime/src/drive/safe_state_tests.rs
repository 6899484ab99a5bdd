//! The inverter's safe states when commands stop.

use super::Plant;
use crate::config::{SafeState, Scenario};
use crate::messages::{Header, VoltageCommand, FLAG_SAFE_STATE, FLAG_STALE_CMD};

fn plant(safe: SafeState) -> (Plant, VoltageCommand) {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenarios/kyslan-pi.toml"
    ))
    .unwrap();
    let mut sc = Scenario::from_toml(&text, "kyslan-pi.toml").unwrap();
    sc.inverter.safe_state = safe;
    sc.mechanics.prescribed_speed_rad_s = Some(70.0);
    let mut p = Plant::new(&sc);
    // Drive 1 A into q at 70 rad/s, then stop commanding.
    let cmd = VoltageCommand {
        hdr: Header::default(),
        u_ab: [0.0, 60.0],
        ..Default::default()
    };
    for k in 0..200 {
        p.sample(k, Some(&cmd));
        p.advance();
    }
    (p, cmd)
}

#[test]
fn held_then_safe_after_the_hold_time() {
    let (mut p, _) = plant(SafeState::ZeroVector);
    let mut flags = Vec::new();
    for k in 200..206 {
        flags.push(p.sample(k, None).hdr.flags);
        p.advance();
    }
    // hold_samples = 3: three held samples, then the safe state.
    assert_eq!(
        flags[0] & (FLAG_STALE_CMD | FLAG_SAFE_STATE),
        FLAG_STALE_CMD
    );
    assert_eq!(flags[2] & FLAG_SAFE_STATE, 0);
    assert_ne!(flags[3] & FLAG_SAFE_STATE, 0);
}

#[test]
fn pulse_blocking_lets_the_current_decay_while_zero_vector_short_circuits() {
    // Below the DC-link voltage (70 rad/s: back-EMF 36 V << 188 V) a coasting inverter
    // carries no current; an active short circuit drives the short-circuit current
    // i_d → −ψ/L_d (here −11.9 A in the limit ω → ∞; at 70 rad/s a braking current flows).
    let (mut pb, _) = plant(SafeState::PulseBlock);
    let (mut zv, _) = plant(SafeState::ZeroVector);
    for k in 200..400 {
        pb.sample(k, None);
        pb.advance();
        zv.sample(k, None);
        zv.advance();
    }
    let i_pb = (libm::pow(pb.x.i_d, 2.0) + libm::pow(pb.x.i_q, 2.0)).sqrt();
    let i_zv = (libm::pow(zv.x.i_d, 2.0) + libm::pow(zv.x.i_q, 2.0)).sqrt();
    assert!(i_pb < 1e-6, "pulse blocking left {i_pb} A");
    assert!(i_zv > 0.5, "active short circuit carries {i_zv} A");
}

#[test]
fn an_overcurrent_trips_at_the_first_sample_above_the_level_and_stays_latched() {
    use crate::messages::FLAG_TRIPPED;
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenarios/kyslan-pi.toml"
    ))
    .unwrap();
    let mut sc = Scenario::from_toml(&text, "kyslan-pi.toml").unwrap();
    sc.mechanics.prescribed_speed_rad_s = Some(0.0);
    // No sensor noise: the measured phase currents are the true ones the trip compares.
    sc.sensors.current_noise_a = 0.0;
    // The same plant without and with a 2 A trip, both driven by a constant 20 V on α at
    // standstill: the current rises towards 20 V / R with the time constant L/R.
    let plain = Plant::new(&sc);
    sc.inverter.i_trip_a = Some(2.0);
    let tripping = Plant::new(&sc);
    let cmd = VoltageCommand {
        u_ab: [20.0, 0.0],
        ..Default::default()
    };
    let mut first_trip = None;
    let (mut a, mut b) = (plain, tripping);
    for k in 0..400u64 {
        let ma = a.sample(k, Some(&cmd));
        let mb = b.sample(k, Some(&cmd));
        let peak = ma.i_abc.iter().fold(0.0f64, |m, i| m.max(i.abs()));
        if first_trip.is_none() {
            // Until the trip, the two plants measure the same currents bit for bit.
            assert_eq!(ma.i_abc, mb.i_abc, "k = {k}");
            if peak > 2.0 {
                first_trip = Some(k);
            } else {
                assert_eq!(ma.u_ab_applied, mb.u_ab_applied, "k = {k}");
                assert_eq!(mb.hdr.flags & FLAG_TRIPPED, 0, "k = {k}");
            }
        }
        if first_trip.is_some() {
            // From the trip on, latched: safe state although every command is fresh.
            assert_eq!(
                mb.hdr.flags & (FLAG_TRIPPED | FLAG_SAFE_STATE),
                FLAG_TRIPPED | FLAG_SAFE_STATE,
                "k = {k}"
            );
            assert_eq!(mb.u_ab_applied, [0.0; 2], "k = {k}");
            assert_eq!(mb.hdr.flags & FLAG_STALE_CMD, 0, "k = {k}");
        }
        a.advance();
        b.advance();
    }
    let k = first_trip.expect("20 V at standstill must drive the current above 2 A");
    assert!(k > 0);
    // The untripped plant stays above the level; the tripped one's current decays (zero
    // vector at standstill: it decays with L/R, towards nothing).
    assert!(libm::hypot(a.x.i_d, a.x.i_q) > 2.0);
    assert!(libm::hypot(b.x.i_d, b.x.i_q) < 0.1 * libm::hypot(a.x.i_d, a.x.i_q));
    // A restarted plant given the tripped state stays tripped.
    let mut c = Plant::new(&sc);
    c.restore(b.truth());
    assert!(c.tripped);
    assert_ne!(c.sample(400, Some(&cmd)).hdr.flags & FLAG_TRIPPED, 0);
}
