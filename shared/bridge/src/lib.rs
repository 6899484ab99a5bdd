//! drivelab's Zenoh bridge (docs/architecture.md, "Across machines (Zenoh)").
//!
//! A drive's bus stops at its machine's edge. The bridge is a process of its own, started by
//! `drivelab run --zenoh-listen`, that reads chosen bus topics (polled subscribers: the
//! real-time senders pay no wake-up for it) and puts them on Zenoh key expressions
//! `drivelab/<bus>/<topic>`, and takes fault requests from Zenoh back onto the bus when the
//! drive allows it. It runs on a core the drive does not use, at nice 10, and never holds
//! anything a real-time stage waits for. The messages stay the bus's `#[repr(C)]` types,
//! framed by [`codec`] with a version and a size check.
//!
//! The other side, [`remote`], is what `drivelab monitor|fault|record --connect` use.
//!
//! This crate is linked by the `drivelab` CLI only; `drivelab-host`, the stage host, does
//! not depend on it (`cargo tree -p drivelab-runtime` shows no zenoh).

pub mod codec;
pub mod link;
pub mod remote;
pub mod serve;
pub mod split;

/// The bus topics the bridge can forward, by their short name (the key's last part).
pub const TOPICS: &[&str] = &[
    "meas", "truth", "est", "iref", "cmd", "wref", "view", "events",
];

/// Topics forwarded when `--zenoh-topics` is not given: what a remote monitor (view,
/// events) and a remote recorder (truth, cmd, wref) need.
pub const DEFAULT_TOPICS: &[&str] = &["truth", "cmd", "wref", "view", "events"];

/// Key expression of bus topic `topic` (short name) of drive `bus`.
pub fn key(bus: &str, topic: &str) -> String {
    format!("drivelab/{bus}/{topic}")
}

/// Key expression of the bridge's queries of drive `bus` (`scenario`, `events`, `history/
/// TOPIC`, `fault`).
pub fn query_key(bus: &str, what: &str) -> String {
    format!("drivelab/{bus}/q/{what}")
}

/// Validates a `--zenoh-topics` list: comma-separated names of [`TOPICS`].
pub fn parse_topics(list: &str) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    for t in list.split(',').map(str::trim).filter(|t| !t.is_empty()) {
        if !TOPICS.contains(&t) {
            return Err(format!(
                "unknown topic '{t}' (the bridge forwards {})",
                TOPICS.join(", ")
            ));
        }
        if !out.iter().any(|o| o == t) {
            out.push(t.to_string());
        }
    }
    if out.is_empty() {
        return Err("no topic to forward".into());
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topic_lists_are_checked_and_keys_named() {
        assert_eq!(parse_topics("cmd, truth,cmd").unwrap(), ["cmd", "truth"]);
        assert_eq!(
            parse_topics("cmd,torque").unwrap_err(),
            "unknown topic 'torque' (the bridge forwards meas, truth, est, iref, cmd, wref, view, events)"
        );
        assert!(parse_topics(" , ").is_err());
        assert_eq!(key("4242", "meas"), "drivelab/4242/meas");
        assert_eq!(query_key("4242", "scenario"), "drivelab/4242/q/scenario");
    }
}
