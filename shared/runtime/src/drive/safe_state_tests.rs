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
