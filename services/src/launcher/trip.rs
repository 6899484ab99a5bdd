//! The inverter's overcurrent trip, reported like a fault: it comes from the trace, so it is
//! the same in every clock.

use super::supervisor::FaultReport;
use drivelab_runtime::config::Scenario;
use drivelab_runtime::messages::FLAG_TRIPPED;
use drivelab_runtime::trace::TraceRow;

/// The trip's fault report: the first sample the plant flagged [`FLAG_TRIPPED`], detected and
/// made safe there (the inverter trips within the sample), the peak current from that sample
/// to the end, and no recovery (the trip is latched). None when the inverter never tripped.
pub(super) fn trip_report(sc: &Scenario, rows: &[TraceRow]) -> Option<FaultReport> {
    let first = rows
        .iter()
        .position(|r| r.plant_flags & FLAG_TRIPPED != 0)?;
    let r = &rows[first];
    let peak = rows[first..]
        .iter()
        .map(|r| r.i_d.hypot(r.i_q))
        .fold(0.0, f64::max);
    Some(FaultReport {
        fault: drivelab_runtime::text::readable_numbers(&format!(
            "overcurrent trip (inverter.i_trip_a = {} A, latched)",
            sc.inverter.i_trip_a.unwrap_or(f64::NAN)
        ))
        .into_owned(),
        service: "plant".into(),
        process: "plant".into(),
        injected_k: r.k,
        injected_t_s: r.t,
        detected_data_path_ms: Some(0.0),
        detected_by: Some("plant".into()),
        detected_supervisor_ms: None,
        safe_state_ms: Some(0.0),
        peak_current_a: peak,
        republished_ms: None,
        speed_recovered_ms: None,
        plant_down: None,
        samples: super::SampleCounts::of(&rows[first..]),
        bus: None,
        window: None,
        why_null: ["republished_ms", "speed_recovered_ms"]
            .into_iter()
            .map(|k| {
                (
                    k,
                    "the trip is latched: the inverter stays in its safe state".into(),
                )
            })
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(k: u64, i_q: f64, flags: u32) -> TraceRow {
        TraceRow {
            k,
            t: k as f64 * 1e-4,
            i_q,
            plant_flags: flags,
            ..Default::default()
        }
    }

    #[test]
    fn the_first_tripped_sample_is_the_fault_and_the_peak_counts_from_there() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/kyslan-pi.toml");
        let mut sc =
            Scenario::from_toml(&std::fs::read_to_string(path).unwrap(), "kyslan-pi.toml").unwrap();
        sc.inverter.i_trip_a = Some(5.0);
        let rows = [
            row(0, 9.0, 0),
            row(1, 4.0, 0),
            row(2, 6.0, FLAG_TRIPPED | 4),
            row(3, 7.0, FLAG_TRIPPED | 4),
            row(4, 1.0, FLAG_TRIPPED | 4),
        ];
        let f = trip_report(&sc, &rows).unwrap();
        assert_eq!((f.injected_k, f.injected_t_s), (2, 2e-4));
        assert_eq!(f.peak_current_a, 7.0);
        assert_eq!(f.safe_state_ms, Some(0.0));
        assert_eq!(f.speed_recovered_ms, None);
        assert!(f.fault.contains("i_trip_a = 5 A"), "{}", f.fault);
        assert!(trip_report(&sc, &rows[..2]).is_none());
        // A tiny level is written as a number a person reads (Rust's `{}` gives 300 digits).
        sc.inverter.i_trip_a = Some(1e-300);
        let f = trip_report(&sc, &rows).unwrap();
        assert!(
            f.fault.contains("i_trip_a = 1e-300 A, latched"),
            "{}",
            f.fault
        );
    }
}
