//! `drivelab run --foxglove`: a small client written from the Foxglove WebSocket protocol's
//! published specification (subprotocol `foxglove.websocket.v1`: `serverInfo` and
//! `advertise` as JSON text, `subscribe`, then binary Message Data frames of opcode 0x01,
//! subscription id u32 LE, timestamp u64 LE, payload) watches a live drive. Its own bus per
//! test; timeouts are watchdogs only.

mod common;
use common::*;
use serde_json::Value;
use std::net::TcpStream;
use std::sync::mpsc;
use std::time::{Duration, Instant};
use tungstenite::client::IntoClientRequest;
use tungstenite::{Message, WebSocket};

const SUBPROTOCOL: &str = "foxglove.websocket.v1";

/// Starts a real-time drive with `--foxglove 127.0.0.1:0` and returns it with the address it
/// printed and the rest of its stderr (read on a thread, so that the pipe never fills).
fn start(
    bus: &str,
    out: &std::path::Path,
    extra: &[&str],
) -> (Drive, String, mpsc::Receiver<String>) {
    let mut args = vec!["--foxglove", "127.0.0.1:0"];
    args.extend_from_slice(extra);
    let mut child = Drive::start(bus, out, &args);
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            let _ = tx.send(line);
        }
    });
    let addr = loop {
        let line = rx
            .recv_timeout(Duration::from_secs(60))
            .expect("watchdog: no Foxglove address printed within 60 s");
        if let Some(a) = line.split("ws://").nth(1) {
            break a.split_whitespace().next().unwrap().to_string();
        }
    };
    (child, addr, rx)
}

fn connect(addr: &str, subprotocol: &str) -> tungstenite::Result<WebSocket<TcpStream>> {
    let mut req = format!("ws://{addr}").into_client_request().unwrap();
    req.headers_mut()
        .insert("sec-websocket-protocol", subprotocol.parse().unwrap());
    let stream = TcpStream::connect(addr).unwrap();
    // Watchdog against a server that stops sending.
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let (ws, res) = tungstenite::client(req, stream).map_err(|e| match e {
        tungstenite::HandshakeError::Failure(e) => e,
        tungstenite::HandshakeError::Interrupted(_) => panic!("handshake interrupted"),
    })?;
    assert_eq!(
        res.headers()["sec-websocket-protocol"],
        SUBPROTOCOL,
        "the server must answer with the subprotocol"
    );
    Ok(ws)
}

fn text(ws: &mut WebSocket<TcpStream>) -> Value {
    match ws.read().expect("read") {
        Message::Text(t) => serde_json::from_str(t.as_str()).unwrap(),
        m => panic!("expected a JSON text message, got {m:?}"),
    }
}

#[test]
fn a_client_of_the_protocol_gets_the_speed_at_the_advertised_rate_equal_to_the_trace() {
    let _g = serial();
    let dir = scratch("speed");
    let bus = bus_id("speed");
    let out = dir.join("run");
    let (child, addr, _stderr) = start(&bus, &out, &["--duration", "3"]);
    // A client without the subprotocol is refused at the handshake.
    assert!(connect(&addr, "json").is_err());
    let mut ws = connect(&addr, SUBPROTOCOL).unwrap();
    let info = text(&mut ws);
    assert_eq!(info["op"], "serverInfo");
    let meta = &info["metadata"];
    let num = |k: &str| -> f64 { meta[k].as_str().unwrap().parse().unwrap() };
    let (rate_hz, sample_hz, decimation) =
        (num("rate_hz:/speed"), num("sample_hz"), num("decimation"));
    assert_eq!(rate_hz * decimation, sample_hz);
    let adv = text(&mut ws);
    assert_eq!(adv["op"], "advertise");
    let speed = adv["channels"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["topic"] == "/speed")
        .expect("a /speed channel");
    assert_eq!(
        (speed["encoding"].as_str(), speed["schemaEncoding"].as_str()),
        (Some("json"), Some("jsonschema"))
    );
    let schema: Value = serde_json::from_str(speed["schema"].as_str().unwrap()).unwrap();
    assert!(schema["properties"]["omega_m"].is_object(), "{schema}");
    let sub_id = 42u32;
    let subscribe = serde_json::json!({ "op": "subscribe", "subscriptions": [{ "id": sub_id, "channelId": speed["id"] }] });
    ws.send(Message::text(subscribe.to_string())).unwrap();
    // Every message until the server closes at the end of the run.
    let mut got: Vec<(u64, Value)> = Vec::new();
    let t0 = Instant::now();
    loop {
        match ws.read() {
            Ok(Message::Binary(b)) => {
                assert_eq!(b[0], 0x01, "opcode of Message Data");
                assert_eq!(u32::from_le_bytes(b[1..5].try_into().unwrap()), sub_id);
                let ts = u64::from_le_bytes(b[5..13].try_into().unwrap());
                got.push((ts, serde_json::from_slice(&b[13..]).unwrap()));
            }
            Ok(Message::Close(_)) => break,
            Ok(Message::Text(t)) => panic!("unexpected text message: {t}"),
            Ok(_) => {}
            Err(tungstenite::Error::ConnectionClosed) => break,
            Err(e) => panic!("stream ended with {e} after {} messages", got.len()),
        }
    }
    let wall_s = t0.elapsed().as_secs_f64();
    let o = wait(child, Duration::from_secs(60), "drivelab run --foxglove");
    assert!(o.status.success(), "the drive failed");
    assert_clean(&bus);
    let rows = drivelab_runtime::trace::read_csv(&out.join("trace.csv")).unwrap();
    let dec = decimation as u64;
    assert!(got.len() >= 100, "only {} messages", got.len());
    eprintln!(
        "{} /speed messages in {wall_s:.2} s of wall time ({:.0} per s), advertised {rate_hz} Hz",
        got.len(),
        got.len() as f64 / wall_s
    );
    let same = |a: &Value, b: f64| match a.as_f64() {
        Some(v) => v == b,
        None => a.is_null() && b.is_nan(),
    };
    for (i, (ts, m)) in got.iter().enumerate() {
        let k = m["k"].as_u64().unwrap();
        // At the advertised rate: every decimation-th sample, none missing, to the last.
        if i > 0 {
            assert_eq!(k, got[i - 1].1["k"].as_u64().unwrap() + dec, "message {i}");
        }
        let r = &rows[k as usize];
        assert_eq!(r.k, k);
        assert_eq!(*ts, (r.t * 1e9).round() as u64, "timestamp of sample {k}");
        assert!(same(&m["omega_m"], r.omega_m), "sample {k}: {m} vs {r:?}");
        assert!(
            same(&m["omega_ref"], r.omega_ref),
            "sample {k}: {m} vs {r:?}"
        );
        assert!(
            same(&m["omega_hat"], r.omega_hat),
            "sample {k}: {m} vs {r:?}"
        );
    }
    let last = got.last().unwrap().1["k"].as_u64().unwrap();
    assert_eq!(
        last,
        (rows.len() as u64 - 1) / dec * dec,
        "the stream reached the end"
    );
}

#[test]
fn an_address_in_use_or_malformed_is_a_one_line_error() {
    let bus = bus_id("busy");
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    assert_run_refused(&bus, &["--foxglove", &addr], "cannot listen");
    assert_run_usage_error(&bus, &["--foxglove", "nowhere:x"], "not HOST:PORT");
    assert_run_usage_error(
        &bus,
        &["--clock", "inprocess", "--foxglove"],
        "needs a drive on a bus",
    );
    assert_clean(&bus);
}
