//! A minimal client of the Foxglove WebSocket protocol (subprotocol `foxglove.websocket.v1`):
//! connects to `drivelab run --foxglove`, subscribes to every advertised channel and prints,
//! when the server closes, how many messages and bytes each channel brought. It keeps off the
//! drive's real-time cores (`rt_cores` in the server's metadata) at nice 10. It is the client
//! of the with/without-client latency measurement (docs/measurements.md).
//!
//! ```sh
//! cargo run --release -p drivelab-services --example foxglove_watch -- 127.0.0.1:8765
//! ```

use std::collections::BTreeMap;
use std::net::TcpStream;
use std::time::{Duration, Instant};
use tungstenite::client::IntoClientRequest;
use tungstenite::Message;

fn main() -> Result<(), Box<dyn core::error::Error>> {
    let addr = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "127.0.0.1:8765".into());
    // The drive may not listen yet: try for up to 30 s.
    let t0 = Instant::now();
    let stream = loop {
        match TcpStream::connect(&addr) {
            Ok(s) => break s,
            Err(_) if t0.elapsed() < Duration::from_secs(30) => {
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(e) => return Err(format!("{addr}: {e}").into()),
        }
    };
    let mut req = format!("ws://{addr}").into_client_request()?;
    req.headers_mut()
        .insert("sec-websocket-protocol", "foxglove.websocket.v1".parse()?);
    let (mut ws, _) = tungstenite::client(req, stream).map_err(|e| format!("{e}"))?;
    let mut topics: BTreeMap<u64, String> = BTreeMap::new();
    let mut counts: BTreeMap<u32, (u64, u64)> = BTreeMap::new();
    let started = Instant::now();
    loop {
        match ws.read() {
            Ok(Message::Text(t)) => {
                let v: serde_json::Value = serde_json::from_str(t.as_str())?;
                if v["op"] == "serverInfo" {
                    // On the drive's machine, keep off its real-time cores.
                    let cores = v["metadata"]["rt_cores"]
                        .as_str()
                        .and_then(|c| c.parse().ok());
                    if let Some(c) = cores {
                        eprintln!("{}", drivelab_runtime::rt::keep_off(c, "client"));
                    }
                }
                if v["op"] == "advertise" {
                    let mut subs = Vec::new();
                    for c in v["channels"].as_array().into_iter().flatten() {
                        let id = c["id"].as_u64().unwrap_or(0);
                        topics.insert(id, c["topic"].as_str().unwrap_or("?").to_string());
                        subs.push(serde_json::json!({ "id": id, "channelId": id }));
                    }
                    let sub = serde_json::json!({ "op": "subscribe", "subscriptions": subs });
                    ws.send(Message::text(sub.to_string()))?;
                }
            }
            Ok(Message::Binary(b)) if b.len() >= 13 && b[0] == 0x01 => {
                let sub = u32::from_le_bytes([b[1], b[2], b[3], b[4]]);
                let c = counts.entry(sub).or_default();
                c.0 += 1;
                c.1 += b.len() as u64;
            }
            Ok(Message::Close(_)) | Err(tungstenite::Error::ConnectionClosed) => break,
            Ok(_) => {}
            Err(e) => return Err(e.into()),
        }
    }
    let s = started.elapsed().as_secs_f64();
    for (sub, (n, bytes)) in &counts {
        let topic = topics.get(&u64::from(*sub)).map_or("?", |t| t.as_str());
        println!(
            "{topic}: {n} messages, {bytes} bytes, {:.1} per wall s",
            *n as f64 / s
        );
    }
    Ok(())
}
