//! `drivelab run --foxglove [ADDR]`: a server of the Foxglove WebSocket protocol
//! (subprotocol `foxglove.websocket.v1`, JSON messages with JSON schemas) that streams a
//! running drive to Foxglove, PlotJuggler or any client of the protocol (docs/foxglove.md).
//!
//! It lives in the launcher, off the real-time path: the recorder hands it the decimated
//! trace and the supervisor the per-second service figures and the event log. Publishing
//! serialises once and offers the message to each client's bounded queue without waiting
//! (a full queue drops it and counts the drop); each client has its own thread that sends
//! and reads. Channels: `/speed`, `/currents`, `/voltages`, `/angle` (every
//! [`Live::decimation`]-th sample), `/services` (per stage, once per second), `/log`.

use crate::expect::usage;
use anyhow::{anyhow, Result};
use serde::Serialize;
use std::collections::HashMap;
use std::f64::consts::PI;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;
use tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tungstenite::{Message, WebSocket};

/// The protocol's WebSocket subprotocol.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";
/// Default address: this machine only, Foxglove's usual port.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8765";
/// Rate of the signal channels, Hz of simulated time.
pub const SIGNAL_RATE_HZ: f64 = 100.0;
/// Messages queued per client before new ones are dropped (about 2 s of the signals).
const QUEUE: usize = 1024;
/// How often a client's thread looks for the client's requests, and an idle server for
/// connections.
const POLL: Duration = Duration::from_millis(20);
/// A client that does not take what is sent is dropped beyond this, bytes.
const MAX_WRITE_BUFFER: usize = 4 << 20;

/// The server's channels, in advertised order (channel id = index + 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Topic {
    /// ω_m, ω* and ω̂, mechanical rad/s.
    Speed,
    /// i_d, i_d*, i_q, i_q*, A.
    Currents,
    /// u_d, u_q, V.
    Voltages,
    /// θ_e, θ̂ and the error θ̂ − θ_e wrapped to [−π, π), electrical rad.
    Angle,
    /// Per stage, per second: rate, misses, latency percentiles.
    Services,
    /// The supervisor's events (`foxglove.Log`).
    Log,
}

const TOPICS: [Topic; 6] = [
    Topic::Speed,
    Topic::Currents,
    Topic::Voltages,
    Topic::Angle,
    Topic::Services,
    Topic::Log,
];

fn signal_schema(title: &str, fields: &[(&str, &str)]) -> String {
    let mut props = vec![
        r#""k":{"type":"integer","description":"sample index"}"#.to_string(),
        r#""t":{"type":"number","description":"t_k, simulated s"}"#.to_string(),
    ];
    for (name, unit) in fields {
        props.push(format!(
            r#""{name}":{{"type":["number","null"],"description":"{unit}"}}"#
        ));
    }
    format!(
        r#"{{"title":"{title}","type":"object","properties":{{{}}}}}"#,
        props.join(",")
    )
}

impl Topic {
    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Topic::Speed => "/speed",
            Topic::Currents => "/currents",
            Topic::Voltages => "/voltages",
            Topic::Angle => "/angle",
            Topic::Services => "/services",
            Topic::Log => "/log",
        }
    }

    fn id(self) -> u32 {
        TOPICS.iter().position(|&t| t == self).unwrap_or(0) as u32 + 1
    }

    fn schema(self) -> (&'static str, String) {
        match self {
            Topic::Speed => (
                "drivelab.Speed",
                signal_schema(
                    "drivelab.Speed",
                    &[
                        ("omega_m", "mechanical rad/s"),
                        ("omega_ref", "mechanical rad/s"),
                        ("omega_hat", "mechanical rad/s"),
                    ],
                ),
            ),
            Topic::Currents => (
                "drivelab.Currents",
                signal_schema(
                    "drivelab.Currents",
                    &[
                        ("i_d", "A"),
                        ("i_d_ref", "A"),
                        ("i_q", "A"),
                        ("i_q_ref", "A"),
                    ],
                ),
            ),
            Topic::Voltages => (
                "drivelab.Voltages",
                signal_schema("drivelab.Voltages", &[("u_d", "V"), ("u_q", "V")]),
            ),
            Topic::Angle => (
                "drivelab.Angle",
                signal_schema(
                    "drivelab.Angle",
                    &[
                        ("theta_e", "electrical rad"),
                        ("theta_hat", "electrical rad"),
                        (
                            "theta_err",
                            "theta_hat - theta_e in [-pi, pi), electrical rad",
                        ),
                    ],
                ),
            ),
            Topic::Services => (
                "drivelab.ServiceSecond",
                crate::trace_mcap::SERVICES_SCHEMA.to_string(),
            ),
            Topic::Log => ("foxglove.Log", crate::trace_mcap::LOG_SCHEMA.to_string()),
        }
    }
}

/// A message for the clients: channel, time (simulated, ns), JSON payload.
type Out = (u32, u64, Arc<[u8]>);

struct Client {
    tx: SyncSender<Out>,
    thread: JoinHandle<()>,
}

/// The server.
pub struct Live {
    addr: SocketAddr,
    decimation: u64,
    stop: Arc<AtomicBool>,
    clients: Arc<Mutex<Vec<Client>>>,
    accept: Mutex<Option<JoinHandle<()>>>,
    dropped: Arc<AtomicU64>,
}

/// `--foxglove ADDR` as a socket address (HOST:PORT, or PORT alone on 127.0.0.1), with a
/// one-line error.
pub fn parse_addr(s: &str) -> Result<SocketAddr> {
    use std::net::ToSocketAddrs;
    let with_host = if s.chars().all(|c| c.is_ascii_digit()) {
        format!("127.0.0.1:{s}")
    } else {
        s.to_string()
    };
    let bad = |why: String| {
        usage(format!(
            "--foxglove '{s}': not HOST:PORT (e.g. {DEFAULT_ADDR}): {why}"
        ))
    };
    let Some((host, port)) = with_host.rsplit_once(':') else {
        return Err(bad("no port".into()));
    };
    if port.parse::<u16>().is_err() {
        return Err(bad(format!(
            "port '{port}' is not a number from 0 to 65535"
        )));
    }
    with_host
        .to_socket_addrs()
        .ok()
        .and_then(|mut a| a.next())
        .ok_or_else(|| bad(format!("cannot resolve host '{host}'")))
}

impl Live {
    /// Listens on `addr` (port 0: any free port) for a drive sampled at `sample_hz` whose
    /// real-time processes run on `rt_cores` (bit i = CPU i); fails with one line when the
    /// address cannot be had (in use, not this machine's). `info` goes into the server's
    /// `serverInfo.metadata`. The server's threads keep off `rt_cores` at nice 10, as the
    /// monitor does (`drivelab_runtime::rt::keep_off`).
    pub fn start(
        addr: SocketAddr,
        sample_hz: f64,
        rt_cores: u64,
        info: &[(&str, String)],
    ) -> Result<Self> {
        let listener = TcpListener::bind(addr)
            .map_err(|e| anyhow!("--foxglove {addr}: cannot listen: {e}"))?;
        let addr = listener.local_addr()?;
        listener.set_nonblocking(true)?;
        let decimation = ((sample_hz / SIGNAL_RATE_HZ).round() as u64).max(1);
        let mut metadata: HashMap<String, String> = info
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect();
        metadata.insert("sample_hz".into(), format!("{sample_hz}"));
        metadata.insert("decimation".into(), decimation.to_string());
        for t in &TOPICS[..4] {
            metadata.insert(
                format!("rate_hz:{}", t.name()),
                format!("{}", sample_hz / decimation as f64),
            );
        }
        metadata.insert("rate_hz:/services".into(), "1".into());
        // A client on this machine keeps off these CPUs (the foxglove_watch example does).
        metadata.insert("rt_cores".into(), rt_cores.to_string());
        metadata.insert(
            "time".into(),
            "message timestamps are simulated time t_k, ns".into(),
        );
        let hello = Arc::new(hello(&metadata)?);
        let stop = Arc::new(AtomicBool::new(false));
        let clients: Arc<Mutex<Vec<Client>>> = Arc::default();
        let dropped = Arc::new(AtomicU64::new(0));
        let accept = {
            let (stop, clients) = (stop.clone(), clients.clone());
            std::thread::Builder::new()
                .name("foxglove".into())
                .spawn(move || {
                    // Before any client thread: they inherit the CPUs and the nice value.
                    drivelab_runtime::rt::keep_off(rt_cores, "Foxglove server");
                    accept_loop(&listener, &stop, &clients, &hello)
                })?
        };
        Ok(Self {
            addr,
            decimation,
            stop,
            clients,
            accept: Mutex::new(Some(accept)),
            dropped,
        })
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Samples between two messages of a signal channel.
    pub fn decimation(&self) -> u64 {
        self.decimation
    }

    /// Clients connected now.
    pub fn clients(&self) -> usize {
        self.clients.lock().map(|c| c.len()).unwrap_or(0)
    }

    /// Offers `msg` on `topic` at `t_ns` to every client (never waits).
    pub fn publish(&self, topic: Topic, t_ns: u64, msg: &impl Serialize) {
        let Ok(mut clients) = self.clients.lock() else {
            return;
        };
        if clients.is_empty() {
            return;
        }
        let Ok(bytes) = serde_json::to_vec(msg) else {
            return;
        };
        let out: Out = (topic.id(), t_ns, bytes.into());
        clients.retain(|c| match c.tx.try_send(out.clone()) {
            Ok(()) => true,
            Err(TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                true
            }
            Err(TrySendError::Disconnected(_)) => false,
        });
    }

    /// Offers sample `row` to the signal channels if it is on the decimation grid.
    pub fn row(&self, row: &drivelab_runtime::trace::TraceRow) {
        if !row.k.is_multiple_of(self.decimation) {
            return;
        }
        let t_ns = crate::trace_mcap::ns(row.t);
        let (k, t) = (row.k, row.t);
        let nan = |v: f64| v.is_finite().then_some(v);
        self.publish(
            Topic::Speed,
            t_ns,
            &serde_json::json!({ "k": k, "t": t, "omega_m": nan(row.omega_m), "omega_ref": nan(row.omega_ref), "omega_hat": nan(row.omega_hat) }),
        );
        self.publish(
            Topic::Currents,
            t_ns,
            &serde_json::json!({ "k": k, "t": t, "i_d": nan(row.i_d), "i_d_ref": nan(row.i_d_ref), "i_q": nan(row.i_q), "i_q_ref": nan(row.i_q_ref) }),
        );
        self.publish(
            Topic::Voltages,
            t_ns,
            &serde_json::json!({ "k": k, "t": t, "u_d": nan(row.u_d), "u_q": nan(row.u_q) }),
        );
        let err = drivelab_control::motor::wrap_2pi(row.theta_hat - row.theta_e + PI) - PI;
        self.publish(
            Topic::Angle,
            t_ns,
            &serde_json::json!({ "k": k, "t": t, "theta_e": nan(row.theta_e), "theta_hat": nan(row.theta_hat), "theta_err": nan(err) }),
        );
    }

    /// Stops: every client gets what is queued for it, then a close; returns the messages
    /// dropped for clients that did not keep up.
    pub fn stop(&self) -> u64 {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(a) = self.accept.lock().ok().and_then(|mut a| a.take()) {
            let _ = a.join();
        }
        let clients = self
            .clients
            .lock()
            .map(|mut c| std::mem::take(&mut *c))
            .unwrap_or_default();
        for c in clients {
            drop(c.tx);
            let _ = c.thread.join();
        }
        self.dropped.load(Ordering::Relaxed)
    }
}

impl Drop for Live {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

/// The `serverInfo` and `advertise` messages every client gets first.
fn hello(metadata: &HashMap<String, String>) -> Result<[String; 2]> {
    let info = serde_json::json!({
        "op": "serverInfo",
        "name": "drivelab",
        "capabilities": [],
        "supportedEncodings": [],
        "metadata": metadata,
        "sessionId": format!("{}", std::process::id()),
    });
    let channels: Vec<_> = TOPICS
        .iter()
        .map(|t| {
            let (name, schema) = t.schema();
            serde_json::json!({
                "id": t.id(),
                "topic": t.name(),
                "encoding": "json",
                "schemaName": name,
                "schema": schema,
                "schemaEncoding": "jsonschema",
            })
        })
        .collect();
    let adv = serde_json::json!({ "op": "advertise", "channels": channels });
    Ok([serde_json::to_string(&info)?, serde_json::to_string(&adv)?])
}

fn accept_loop(
    listener: &TcpListener,
    stop: &AtomicBool,
    clients: &Mutex<Vec<Client>>,
    hello: &Arc<[String; 2]>,
) {
    while !stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((stream, _)) => {
                let (tx, rx) = sync_channel(QUEUE);
                let hello = hello.clone();
                let spawned = std::thread::Builder::new()
                    .name("foxglove-client".into())
                    .spawn(move || {
                        // A client that leaves or misbehaves ends its own thread only.
                        let _ = serve_client(stream, &hello, &rx);
                    });
                if let (Ok(thread), Ok(mut c)) = (spawned, clients.lock()) {
                    c.push(Client { tx, thread });
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => std::thread::sleep(POLL),
            Err(_) => std::thread::sleep(POLL),
        }
    }
}

/// The handshake: only a client that offers the protocol's subprotocol is accepted.
fn handshake(stream: TcpStream) -> Result<WebSocket<TcpStream>> {
    let config = tungstenite::protocol::WebSocketConfig::default()
        .max_write_buffer_size(MAX_WRITE_BUFFER)
        .max_message_size(Some(1 << 20));
    // tungstenite's callback type: its error is the HTTP response sent back.
    #[allow(clippy::result_large_err)]
    let check = |req: &Request, mut res: Response| -> Result<Response, ErrorResponse> {
        let offered = req
            .headers()
            .get_all("sec-websocket-protocol")
            .iter()
            .filter_map(|h| h.to_str().ok())
            .flat_map(|h| h.split(','))
            .any(|p| p.trim() == SUBPROTOCOL);
        if !offered {
            let mut e = ErrorResponse::new(Some(format!(
                "this server speaks the subprotocol {SUBPROTOCOL} only"
            )));
            *e.status_mut() = tungstenite::http::StatusCode::BAD_REQUEST;
            return Err(e);
        }
        res.headers_mut().insert(
            "sec-websocket-protocol",
            tungstenite::http::HeaderValue::from_static(SUBPROTOCOL),
        );
        Ok(res)
    };
    stream.set_nonblocking(false)?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    let ws = tungstenite::accept_hdr_with_config(stream, check, Some(config))
        .map_err(|e| anyhow!("handshake: {e}"))?;
    ws.get_ref().set_nonblocking(true)?;
    Ok(ws)
}

/// One client: the hello, then what it subscribed to, until it leaves or the server stops
/// (its queue's sender dropped: what is queued is sent, then a close).
fn serve_client(stream: TcpStream, hello: &[String; 2], rx: &Receiver<Out>) -> Result<()> {
    let mut ws = handshake(stream)?;
    for h in hello {
        ws.send(Message::text(h.clone()))
            .or_else(|e| would_block(e, ()))?;
    }
    // Subscription id per channel id.
    let mut subs: HashMap<u32, u32> = HashMap::new();
    let mut frame = Vec::with_capacity(256);
    loop {
        let next = rx.recv_timeout(POLL);
        let ended = matches!(next, Err(RecvTimeoutError::Disconnected));
        let mut send = |(ch, t_ns, data): Out, ws: &mut WebSocket<TcpStream>| -> Result<()> {
            if let Some(&sub) = subs.get(&ch) {
                // Message Data: opcode 0x01, subscription id (u32 LE), timestamp (u64 LE, ns).
                frame.clear();
                frame.push(0x01);
                frame.extend_from_slice(&sub.to_le_bytes());
                frame.extend_from_slice(&t_ns.to_le_bytes());
                frame.extend_from_slice(&data);
                ws.write(Message::binary(frame.clone()))
                    .or_else(|e| would_block(e, ()))?;
            }
            Ok(())
        };
        if let Ok(m) = next {
            send(m, &mut ws)?;
            for m in rx.try_iter() {
                send(m, &mut ws)?;
            }
        }
        ws.flush().or_else(|e| would_block(e, ()))?;
        if ended {
            // Give the client what is still buffered, then close.
            let _ = ws.get_ref().set_nonblocking(false);
            let _ = ws.get_ref().set_write_timeout(Some(Duration::from_secs(2)));
            let _ = ws.flush();
            let _ = ws.close(None);
            let _ = ws.flush();
            return Ok(());
        }
        loop {
            match ws.read() {
                Ok(Message::Text(t)) => handle_request(t.as_str(), &mut subs, &mut ws)?,
                Ok(Message::Close(_)) => return Ok(()),
                Ok(_) => {}
                Err(tungstenite::Error::Io(e)) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    break
                }
                Err(e) => return Err(e.into()),
            }
        }
    }
}

fn would_block<T>(e: tungstenite::Error, ok: T) -> Result<T> {
    match e {
        tungstenite::Error::Io(io) if io.kind() == std::io::ErrorKind::WouldBlock => Ok(ok),
        e => Err(e.into()),
    }
}

/// `subscribe` and `unsubscribe`; anything else gets a warning status.
fn handle_request(
    text: &str,
    subs: &mut HashMap<u32, u32>,
    ws: &mut WebSocket<TcpStream>,
) -> Result<()> {
    let v: serde_json::Value = serde_json::from_str(text).unwrap_or_default();
    let list = |key: &str| v[key].as_array().cloned().unwrap_or_default();
    let mut problems = Vec::new();
    match v["op"].as_str() {
        Some("subscribe") => {
            for s in list("subscriptions") {
                match (s["id"].as_u64(), s["channelId"].as_u64()) {
                    (Some(id), Some(ch)) if TOPICS.iter().any(|t| u64::from(t.id()) == ch) => {
                        subs.insert(ch as u32, id as u32);
                    }
                    _ => problems.push(format!("no such channel: {s}")),
                }
            }
        }
        Some("unsubscribe") => {
            for id in list("subscriptionIds").iter().filter_map(|i| i.as_u64()) {
                subs.retain(|_, s| u64::from(*s) != id);
            }
        }
        op => problems.push(format!("unsupported request {op:?}")),
    }
    for p in problems {
        let status = serde_json::json!({ "op": "status", "level": 1, "message": p });
        ws.write(Message::text(status.to_string()))
            .or_else(|e| would_block(e, ()))?;
    }
    Ok(())
}

/// Refuses `--foxglove` with a clock that has no bus.
pub fn check_clock(inprocess: bool) -> Result<()> {
    if inprocess {
        return Err(usage(
            "--foxglove needs a drive on a bus: use --clock realtime or lockstep".into(),
        ));
    }
    Ok(())
}
