//! The bridge's wire format: the bus's `#[repr(C)]` messages as bytes, framed with a
//! version and a size check (docs/architecture.md, "Across machines (Zenoh)").
//!
//! A frame is a 16-byte head followed by `count` messages of one type, each
//! `size_of::<T>()` bytes, copied as they are in memory:
//!
//! | bytes | field | value |
//! |---|---|---|
//! | 0..4 | magic | `MAGIC` in the sender's byte order (a big-endian peer fails here) |
//! | 4..6 | version | [`VERSION`] |
//! | 6..8 | kind | [`Wire::KIND`] of the type |
//! | 8..12 | size | `size_of::<T>()` |
//! | 12..16 | count | messages that follow, 1 to [`MAX_COUNT`] |
//!
//! Decoding checks all five and the frame's length, then every message's plausibility
//! ([`Wire::plausible`]: finite values, counts within their arrays); anything else is a
//! [`Reject`], which the bridge counts and drops. Both ends are little-endian 64-bit
//! machines of the same layout (x86_64, aarch64).

use drivelab_runtime::messages::{
    CurrentRef, Estimate, Finite, Measurement, PlantTruth, SpeedRef, VoltageCommand,
};
use drivelab_runtime::telemetry::{
    DriveView, EventEntry, FaultRequest, FAULT_KILL, FAULT_STOP, MAX_STAGES, VIEW_POINTS,
};

/// First four bytes of every frame ("DLZB" read as a little-endian u32).
pub const MAGIC: u32 = u32::from_le_bytes(*b"DLZB");
/// Version of the frame layout and of the message types it carries. Bump it whenever a
/// message of `drivelab_runtime::messages` or `telemetry` changes.
pub const VERSION: u16 = 2;
/// Length of a frame's head, bytes.
pub const HEAD: usize = 16;
/// Most messages in one frame (the bridge batches what arrived since its last poll).
pub const MAX_COUNT: usize = 4096;

/// A message type that may cross the bridge.
///
/// # Safety
///
/// Implement only for `#[repr(C)]` types without padding bytes whose fields are integers,
/// floats or arrays of them: every bit pattern must be a valid value (decoding copies
/// bytes into it), and every byte must be initialised (encoding reads them all).
pub unsafe trait Wire: Copy + 'static {
    /// Identifies the type on the wire.
    const KIND: u16;
    /// Name for messages and counters.
    const NAME: &'static str;
    /// True when the decoded value is one a drive could have sent.
    fn plausible(&self) -> bool;
}

macro_rules! wire_finite {
    ($t:ty, $kind:expr, $name:expr) => {
        // SAFETY: a #[repr(C)] message of `drivelab_runtime::messages`: a `Header` (u64 ×
        // 3, u32 × 2) and f64 fields or arrays, all 8-byte aligned, so no padding; any bit
        // pattern is a valid value. `layouts_have_no_padding` checks the sizes.
        unsafe impl Wire for $t {
            const KIND: u16 = $kind;
            const NAME: &'static str = $name;
            fn plausible(&self) -> bool {
                self.is_finite()
            }
        }
    };
}

wire_finite!(Measurement, 1, "meas");
wire_finite!(PlantTruth, 2, "truth");
wire_finite!(Estimate, 3, "est");
wire_finite!(CurrentRef, 4, "iref");
wire_finite!(VoltageCommand, 5, "cmd");
wire_finite!(SpeedRef, 6, "wref");

// SAFETY: `DriveView` is #[repr(C)]; its fields are integers, f64, byte arrays and arrays
// of `ServiceView`/`TracePoint` (likewise integers and f64 only); its `reserved` field
// fills the one gap, so it has no padding (`layouts_have_no_padding`).
unsafe impl Wire for DriveView {
    const KIND: u16 = 7;
    const NAME: &'static str = "view";
    fn plausible(&self) -> bool {
        self.n_stages as usize <= MAX_STAGES
            && self.n_points as usize <= VIEW_POINTS
            && self.sample_hz.is_finite()
            && self.sample_hz > 0.0
    }
}

// SAFETY: #[repr(C)] f64, u64, u64, [u8; 120]: 144 bytes, no padding; any bit pattern is a
// valid value (the text is read with `get_str`, which takes invalid UTF-8 as "?").
unsafe impl Wire for EventEntry {
    const KIND: u16 = 8;
    const NAME: &'static str = "events";
    fn plausible(&self) -> bool {
        self.t_wall_s.is_finite()
    }
}

// SAFETY: #[repr(C)] four u32: 16 bytes, no padding; any bit pattern is a valid value.
unsafe impl Wire for FaultRequest {
    const KIND: u16 = 9;
    const NAME: &'static str = "fault-request";
    fn plausible(&self) -> bool {
        matches!(self.kind, FAULT_KILL | FAULT_STOP) && (self.service as usize) < MAX_STAGES
    }
}

/// Why a frame was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reject {
    /// Shorter than a head, or not `HEAD + count × size` bytes long.
    Length,
    /// Not a drivelab frame (or a big-endian sender).
    Magic,
    /// Another version of the layout.
    Version(u16),
    /// A frame of another message type than the key expects.
    Kind(u16),
    /// The sender's message size differs from ours.
    Size(u32),
    /// No message, or more than [`MAX_COUNT`].
    Count(u32),
    /// A message with a value no drive sends (NaN, ∞, an absurd magnitude or count).
    Implausible,
}

impl std::fmt::Display for Reject {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Reject::Length => write!(f, "frame length does not match its head"),
            Reject::Magic => write!(f, "not a drivelab frame (bad magic)"),
            Reject::Version(v) => write!(f, "frame version {v}, expected {VERSION}"),
            Reject::Kind(k) => write!(f, "frame of message kind {k} on the wrong key"),
            Reject::Size(s) => write!(f, "message size {s} does not match this build's"),
            Reject::Count(c) => write!(f, "frame of {c} messages (1..{MAX_COUNT})"),
            Reject::Implausible => write!(f, "a message with implausible values"),
        }
    }
}

impl std::error::Error for Reject {}

/// Appends a frame of `msgs` to `out` (cleared first). Panics on an empty slice or more
/// than [`MAX_COUNT`] messages: callers batch within those bounds.
pub fn encode_into<T: Wire>(msgs: &[T], out: &mut Vec<u8>) {
    assert!(
        !msgs.is_empty() && msgs.len() <= MAX_COUNT,
        "a frame holds 1..{MAX_COUNT} messages"
    );
    let size = std::mem::size_of::<T>();
    out.clear();
    out.reserve(HEAD + std::mem::size_of_val(msgs));
    out.extend_from_slice(&MAGIC.to_ne_bytes());
    out.extend_from_slice(&VERSION.to_ne_bytes());
    out.extend_from_slice(&T::KIND.to_ne_bytes());
    out.extend_from_slice(&(size as u32).to_ne_bytes());
    out.extend_from_slice(&(msgs.len() as u32).to_ne_bytes());
    // SAFETY: `msgs` is a valid slice of `T`, which (per `Wire`) has no padding, so all its
    // `size_of_val(msgs)` bytes are initialised and may be read as u8.
    let bytes = unsafe {
        std::slice::from_raw_parts(msgs.as_ptr().cast::<u8>(), std::mem::size_of_val(msgs))
    };
    out.extend_from_slice(bytes);
}

/// A frame of `msgs`.
pub fn encode<T: Wire>(msgs: &[T]) -> Vec<u8> {
    let mut v = Vec::new();
    encode_into(msgs, &mut v);
    v
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_ne_bytes([b[at], b[at + 1]])
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_ne_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// Checks a frame's head for type `T` and returns the number of messages in it.
pub fn check<T: Wire>(frame: &[u8]) -> Result<usize, Reject> {
    if frame.len() < HEAD {
        return Err(Reject::Length);
    }
    if u32_at(frame, 0) != MAGIC {
        return Err(Reject::Magic);
    }
    let version = u16_at(frame, 4);
    if version != VERSION {
        return Err(Reject::Version(version));
    }
    let kind = u16_at(frame, 6);
    if kind != T::KIND {
        return Err(Reject::Kind(kind));
    }
    let size = u32_at(frame, 8);
    if size as usize != std::mem::size_of::<T>() {
        return Err(Reject::Size(size));
    }
    let count = u32_at(frame, 12);
    if count == 0 || count as usize > MAX_COUNT {
        return Err(Reject::Count(count));
    }
    if frame.len() != HEAD + count as usize * size as usize {
        return Err(Reject::Length);
    }
    Ok(count as usize)
}

/// Decodes a frame of `T`s into `out` (cleared first). On any [`Reject`] `out` is left
/// empty: a frame is taken whole or not at all.
pub fn decode_into<T: Wire>(frame: &[u8], out: &mut Vec<T>) -> Result<(), Reject> {
    out.clear();
    let count = check::<T>(frame)?;
    let size = std::mem::size_of::<T>();
    for i in 0..count {
        let at = HEAD + i * size;
        let src = &frame[at..at + size];
        // SAFETY: `src` holds exactly size_of::<T>() bytes (checked above); `T` accepts any
        // bit pattern (per `Wire`); read_unaligned copes with the frame's alignment.
        let m: T = unsafe { std::ptr::read_unaligned(src.as_ptr().cast::<T>()) };
        if !m.plausible() {
            out.clear();
            return Err(Reject::Implausible);
        }
        out.push(m);
    }
    Ok(())
}

/// Decodes a frame of `T`s.
pub fn decode<T: Wire>(frame: &[u8]) -> Result<Vec<T>, Reject> {
    let mut v = Vec::new();
    decode_into(frame, &mut v)?;
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivelab_runtime::messages::Header;
    use drivelab_runtime::telemetry::{put_str, ServiceStatus, ServiceView, TracePoint};
    use std::mem::size_of;

    fn cmd(k: u64) -> VoltageCommand {
        VoltageCommand {
            hdr: Header {
                k,
                t_pub_ns: 7,
                ..Default::default()
            },
            u_ab: [1.5, -2.25],
            omega_ref: 70.0,
            ..Default::default()
        }
    }

    #[test]
    fn layouts_have_no_padding() {
        // The sum of the fields' sizes: any padding would make the type larger.
        assert_eq!(size_of::<Header>(), 8 * 3 + 4 * 2);
        assert_eq!(size_of::<Measurement>(), 32 + 8 * 6);
        assert_eq!(size_of::<PlantTruth>(), 32 + 8 * 11);
        assert_eq!(size_of::<Estimate>(), 32 + 8 * 2);
        assert_eq!(size_of::<CurrentRef>(), 32 + 8 * 3);
        assert_eq!(size_of::<VoltageCommand>(), 32 + 8 * 9);
        assert_eq!(size_of::<SpeedRef>(), 32 + 8 * 3);
        assert_eq!(size_of::<EventEntry>(), 8 * 3 + 120);
        assert_eq!(size_of::<FaultRequest>(), 4 * 4);
        let hist = 8 * 2 + 4 * drivelab_runtime::telemetry::BUCKETS;
        let status = 32 + 4 * 2 + 8 * 6 + 3 * hist;
        assert_eq!(size_of::<ServiceStatus>(), status);
        assert_eq!(size_of::<ServiceView>(), status + 4 * 4 + 8);
        assert_eq!(size_of::<TracePoint>(), 8 * 7);
        let view = 32
            + 8 * 2
            + 4 * 2
            + 8 * 2
            + 48
            + 4 * 2
            + 32 * MAX_STAGES
            + size_of::<ServiceView>() * MAX_STAGES
            + size_of::<TracePoint>() * VIEW_POINTS;
        assert_eq!(size_of::<DriveView>(), view);
    }

    #[test]
    fn a_frame_round_trips_bit_for_bit() {
        let msgs = [cmd(3), cmd(4), cmd(5)];
        let frame = encode(&msgs);
        assert_eq!(frame.len(), HEAD + 3 * size_of::<VoltageCommand>());
        assert_eq!(decode::<VoltageCommand>(&frame).unwrap(), msgs);
        let mut v = DriveView {
            sample_hz: 10_000.0,
            n_stages: 2,
            ..Default::default()
        };
        put_str(&mut v.stage_names[1], "observer");
        v.services[1].status.cycle.record_ns(31_000);
        let back = decode::<DriveView>(&encode(&[v])).unwrap();
        assert_eq!(back, [v]);
        assert_eq!(back[0].stage_name(1), "observer");
    }

    #[test]
    fn foreign_and_malformed_frames_are_rejected_whole() {
        let good = encode(&[cmd(1), cmd(2)]);
        let mut out = vec![cmd(9)];
        let mut bad = |f: &dyn Fn(&mut Vec<u8>), want: Reject| {
            let mut frame = good.clone();
            f(&mut frame);
            assert_eq!(decode_into::<VoltageCommand>(&frame, &mut out), Err(want));
            assert!(out.is_empty(), "a rejected frame yields nothing");
        };
        bad(&|f| f.truncate(10), Reject::Length);
        bad(&|f| f.truncate(f.len() - 1), Reject::Length);
        bad(&|f| f.push(0), Reject::Length);
        bad(&|f| f[0] = b'X', Reject::Magic);
        // A big-endian sender writes the magic the other way round.
        bad(&|f| f[..4].reverse(), Reject::Magic);
        // A frame of another layout version (the one before this, and the one after).
        bad(
            &|f| f[4] = (VERSION - 1) as u8,
            Reject::Version(VERSION - 1),
        );
        bad(
            &|f| f[4] = (VERSION + 1) as u8,
            Reject::Version(VERSION + 1),
        );
        bad(&|f| f[6] = 1, Reject::Kind(1));
        bad(
            &|f| f[8] += 8,
            Reject::Size(size_of::<VoltageCommand>() as u32 + 8),
        );
        bad(
            &|f| f[12..16].copy_from_slice(&0u32.to_ne_bytes()),
            Reject::Count(0),
        );
        bad(
            &|f| f[12..16].copy_from_slice(&5000u32.to_ne_bytes()),
            Reject::Count(5000),
        );
        // The second message's u_ab[0] (after the head, the first message and its header)
        // set to NaN: the whole frame goes, not just that message.
        let at = HEAD + size_of::<VoltageCommand>() + 32;
        bad(
            &|f| f[at..at + 8].copy_from_slice(&f64::NAN.to_ne_bytes()),
            Reject::Implausible,
        );
        bad(
            &|f| f[at..at + 8].copy_from_slice(&1e30f64.to_ne_bytes()),
            Reject::Implausible,
        );
        // Another message type with the same framing is no command.
        let est = encode(&[Estimate::default()]);
        assert_eq!(decode::<VoltageCommand>(&est), Err(Reject::Kind(3)));
        assert_eq!(decode::<VoltageCommand>(b""), Err(Reject::Length));
        assert_eq!(
            decode::<VoltageCommand>(&[0u8; 200]),
            Err(Reject::Magic),
            "zeros are no frame"
        );
    }

    #[test]
    fn a_fault_request_must_name_a_known_kind_and_a_stage_slot() {
        let ok = FaultRequest {
            kind: FAULT_KILL,
            service: 3,
            stop_ms: 0,
            pid: 1,
        };
        assert!(decode::<FaultRequest>(&encode(&[ok])).is_ok());
        for bad in [
            FaultRequest { kind: 7, ..ok },
            FaultRequest {
                service: MAX_STAGES as u32,
                ..ok
            },
        ] {
            assert_eq!(
                decode::<FaultRequest>(&encode(&[bad])),
                Err(Reject::Implausible)
            );
        }
        let v = DriveView {
            n_stages: MAX_STAGES as u32 + 1,
            sample_hz: 1.0,
            ..Default::default()
        };
        assert_eq!(decode::<DriveView>(&encode(&[v])), Err(Reject::Implausible));
    }
}
