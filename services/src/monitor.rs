//! `drivelab monitor`: a live terminal view of a running drive (ratatui).
//!
//! It attaches to the supervisor's telemetry (see `drivelab_runtime::telemetry`), never to the
//! real-time processes' topics, so attaching, watching and detaching cost the drive nothing.
//! It shows per service the process state, rate, wake-up lateness and execution time
//! (p99 and max since the service started), deadline misses and stale or rejected inputs; the
//! last 2.5 s of speed against its reference and of i_d and i_q; and the supervisor's event
//! log. `k` and `s` ask the supervisor to kill or freeze the selected stage's process, after a
//! confirmation.

use anyhow::{anyhow, bail, Context, Result};
#[cfg(feature = "tui")]
use drivelab_runtime::config::SERVICES;
use drivelab_runtime::telemetry::*;
use iceoryx2::prelude::*;
#[cfg(feature = "tui")]
use ratatui::crossterm::event::{self, Event, KeyCode, KeyEventKind, KeyModifiers};
#[cfg(feature = "tui")]
use ratatui::layout::{Constraint, Layout, Rect};
#[cfg(feature = "tui")]
use ratatui::style::{Color, Modifier, Style};
#[cfg(feature = "tui")]
use ratatui::symbols::Marker;
#[cfg(feature = "tui")]
use ratatui::text::{Line, Span};
#[cfg(feature = "tui")]
use ratatui::widgets::{Axis, Block, Cell, Chart, Dataset, GraphType, Paragraph, Row, Table};
#[cfg(feature = "tui")]
use ratatui::Frame;
#[cfg(feature = "tui")]
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Options of `drivelab monitor`.
#[derive(Debug, Clone)]
pub struct MonitorOptions {
    /// Where the drive is.
    pub target: Target,
    /// Screen refresh period.
    pub refresh: Duration,
    /// Freeze time of a stop fault, ms.
    pub stop_ms: u32,
    /// Print one frame as text (width, height) instead of running the terminal UI.
    pub print: Option<(u16, u16)>,
}

/// Where a drive is: on this machine's bus, or behind its Zenoh bridge (`--connect`;
/// docs/architecture.md, "Across machines (Zenoh)").
#[derive(Debug, Clone)]
pub enum Target {
    /// The bus id of a drive on this machine.
    Bus(String),
    /// A drive started with `drivelab run --zenoh-listen`.
    Remote {
        /// Its bridge's endpoint, e.g. tcp/192.168.1.20:7447.
        endpoint: String,
        /// Its bus id, needed only when the bridge serves several drives.
        bus: Option<String>,
        /// Zenoh configuration file (TLS, access control).
        config: Option<std::path::PathBuf>,
    },
}

/// The monitor's ports on the bus.
struct LocalPorts {
    view_rx: PlainReceiver<DriveView>,
    events_rx: PlainReceiver<EventEntry>,
    req_tx: PlainSender<FaultRequest>,
    _topics: (Plain<DriveView>, Plain<EventEntry>, Plain<FaultRequest>),
    _node: Node<ipc::Service>,
}

/// The monitor's subscriptions to a remote drive, and what it had missed when it attached.
#[cfg(feature = "zenoh")]
struct RemotePorts {
    remote: drivelab_bridge::remote::Remote,
    view: drivelab_bridge::remote::Feed<DriveView>,
    events: drivelab_bridge::remote::Feed<EventEntry>,
    missed_view: std::cell::Cell<Option<DriveView>>,
    missed_events: std::cell::RefCell<std::collections::VecDeque<EventEntry>>,
}

/// A drive the monitor is attached to.
enum Attached {
    Local(Box<LocalPorts>),
    #[cfg(feature = "zenoh")]
    Remote(Box<RemotePorts>),
}

impl Attached {
    /// The drive's bus id, with its endpoint when remote.
    fn label(&self, target: &Target) -> String {
        match (self, target) {
            #[cfg(feature = "zenoh")]
            (Attached::Remote(r), _) => format!("{} at {}", r.remote.bus(), r.remote.endpoint()),
            (_, Target::Bus(b)) => b.clone(),
            (_, Target::Remote { endpoint, .. }) => endpoint.clone(),
        }
    }

    fn try_view(&self) -> Result<Option<DriveView>> {
        match self {
            Attached::Local(l) => l.view_rx.try_recv(),
            #[cfg(feature = "zenoh")]
            Attached::Remote(r) => match r.missed_view.take() {
                Some(v) => Ok(Some(v)),
                None => r.remote.next(&r.view),
            },
        }
    }

    fn try_event(&self) -> Result<Option<EventEntry>> {
        match self {
            Attached::Local(l) => l.events_rx.try_recv(),
            #[cfg(feature = "zenoh")]
            Attached::Remote(r) => match r.missed_events.borrow_mut().pop_front() {
                Some(e) => Ok(Some(e)),
                None => r.remote.next(&r.events),
            },
        }
    }

    /// Sends a fault request; a remote drive's refusal is the error.
    fn send(&self, req: &FaultRequest) -> Result<()> {
        match self {
            Attached::Local(l) => l.req_tx.send(req),
            #[cfg(feature = "zenoh")]
            Attached::Remote(r) => r.remote.request_fault(req),
        }
    }
}

fn attach(target: &Target) -> Result<Attached> {
    match target {
        Target::Bus(bus) => attach_local(bus).map(|l| Attached::Local(Box::new(l))),
        #[cfg(feature = "zenoh")]
        Target::Remote {
            endpoint,
            bus,
            config,
        } => {
            let remote = drivelab_bridge::remote::Remote::connect(
                endpoint,
                bus.as_deref(),
                config.as_deref(),
                Duration::ZERO,
            )?;
            // Subscribe first, then fetch what was missed: nothing falls in between (the
            // log drops events it already has).
            let view = remote.feed::<DriveView>()?;
            let events = remote.feed::<EventEntry>()?;
            let (missed_view, missed) = remote.catch_up()?;
            Ok(Attached::Remote(Box::new(RemotePorts {
                remote,
                view,
                events,
                missed_view: std::cell::Cell::new(missed_view),
                missed_events: std::cell::RefCell::new(missed.into()),
            })))
        }
        #[cfg(not(feature = "zenoh"))]
        Target::Remote { .. } => bail!(
            "this drivelab was built without Zenoh (cargo feature `zenoh`); --connect needs it"
        ),
    }
}

fn attach_local(bus: &str) -> Result<LocalPorts> {
    drivelab_runtime::bus::check_bus_id(bus)?;
    // iceoryx2 must not write to the screen the UI owns.
    iceoryx2::prelude::set_log_level(LogLevel::Fatal);
    let cfg = drivelab_runtime::bus::config(bus)?;
    let name = ServiceName::new(TOPIC_VIEW).map_err(|e| anyhow!("{e:?}"))?;
    let exists =
        ipc::Service::does_exist(&name, &cfg, MessagingPattern::PublishSubscribe).unwrap_or(false);
    if !exists {
        // Another user's drive is invisible, not absent: say so.
        let root = drivelab_runtime::bus::root_path(bus);
        if let Err(e) = std::fs::read_dir(&root) {
            if e.kind() == std::io::ErrorKind::PermissionDenied {
                use std::os::unix::fs::MetadataExt;
                let owner = std::fs::metadata(&root)
                    .map(|m| format!("uid {}", m.uid()))
                    .unwrap_or_else(|_| "another user".into());
                bail!(
                    "bus '{bus}': permission denied: its files ({root}) belong to {owner}; run as that user or as root"
                );
            }
        }
        bail!("no drive on bus '{bus}': start one with `drivelab run --bus {bus}`");
    }
    let node = drivelab_runtime::bus::node(bus, "monitor")?;
    let open = |node: Node<ipc::Service>| -> Result<LocalPorts> {
        let view = open_existing::<DriveView>(&node, TOPIC_VIEW)?;
        let events = open_existing::<EventEntry>(&node, TOPIC_EVENTS)?;
        let req = open_existing::<FaultRequest>(&node, TOPIC_FAULT_REQ)?;
        Ok(LocalPorts {
            view_rx: PlainReceiver::new(&view, 4)?,
            events_rx: PlainReceiver::new(&events, 64)?,
            req_tx: PlainSender::new(&req)?,
            _topics: (view, events, req),
            _node: node,
        })
    };
    open(node)
        .with_context(|| format!("cannot attach to the drive on bus '{bus}' (did it just end?)"))
}

/// `drivelab fault`: asks the supervisor of the drive on `bus` to kill or freeze (for
/// `stop_ms`) the process of `stage`, as the monitor's `k` and `s` do, and waits for its
/// answer. The supervisor signals its own child, so no other process can be hit, whatever
/// its name or pid. Returns the supervisor's event text.
pub fn request_fault(target: &Target, kind: u32, stage: &str, stop_ms: u32) -> Result<String> {
    if kind == FAULT_STOP && !(1..=60_000).contains(&stop_ms) {
        return Err(crate::expect::usage(format!(
            "a stop lasts 1 ms to 60 s, not {stop_ms} ms"
        )));
    }
    let a = attach(target)?;
    let bus = a.label(target);
    let t = Instant::now();
    let answer_within = Duration::from_secs(3);
    // The drive's view names its stages; the event history tells which events are old.
    let mut view = None;
    let mut last_seq = None;
    while t.elapsed() < Duration::from_millis(300) || view.is_none() {
        while let Some(v) = a.try_view()? {
            view = Some(v);
        }
        while let Some(e) = a.try_event()? {
            last_seq = Some(e.seq);
        }
        if t.elapsed() > answer_within {
            bail!("the drive on bus '{bus}' publishes no view (did it just end?)");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let view = view.expect("loop ends with a view");
    let stages: Vec<&str> = (0..view.stages()).map(|i| view.stage_name(i)).collect();
    let Some(i) = stages.iter().position(|s| *s == stage) else {
        bail!(
            "no stage '{stage}' in the drive on bus '{bus}' (its stages: {})",
            stages.join(", ")
        );
    };
    let me = std::process::id();
    a.send(&FaultRequest {
        kind,
        service: i as u32,
        stop_ms,
        pid: me,
    })?;
    let mine = format!("(requested by pid {me})");
    let t = Instant::now();
    while t.elapsed() < answer_within {
        while let Some(e) = a.try_event()? {
            if last_seq.is_some_and(|s| e.seq <= s) {
                continue;
            }
            let text = e.text();
            if text.starts_with("inject ") && text.contains(&mine) {
                return Ok(text.to_string());
            }
            if text.starts_with("inject-refused")
                || text.starts_with(&format!("inject-skipped {stage}:"))
            {
                bail!("the supervisor did not inject it: {text}");
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    bail!("the supervisor of bus '{bus}' did not answer within {answer_within:?}")
}

#[cfg(feature = "tui")]
/// One line of a chart: label, colour, (t, value) points.
type Series<'a> = (&'a str, Color, Vec<(f64, f64)>);

#[cfg(feature = "tui")]
/// What the screen shows.
struct Ui {
    bus: String,
    view: Option<Box<DriveView>>,
    events: VecDeque<EventEntry>,
    selected: usize,
    confirm: Option<u32>,
    message: String,
    ended: bool,
    stop_ms: u32,
}

#[cfg(feature = "tui")]
const LOG_KEEP: usize = 200;

/// What a stage's figures show before its first status.
#[cfg(feature = "tui")]
const NO_STATUS: &str = "–";

#[cfg(feature = "tui")]
impl Ui {
    fn new(o: &MonitorOptions) -> Self {
        Self {
            bus: match &o.target {
                Target::Bus(b) => b.clone(),
                Target::Remote { endpoint, .. } => endpoint.clone(),
            },
            view: None,
            events: VecDeque::new(),
            selected: 0,
            confirm: None,
            message: String::new(),
            ended: false,
            stop_ms: o.stop_ms,
        }
    }

    /// Stages shown: the drive's (from its view), the four built-in ones before it arrives.
    fn n_stages(&self) -> usize {
        self.view
            .as_ref()
            .map_or(SERVICES.len(), |v| v.stages().max(1))
    }

    /// Name of stage `i`.
    fn stage_name(&self, i: usize) -> String {
        match &self.view {
            Some(v) => v.stage_name(i).to_string(),
            None => SERVICES.get(i).unwrap_or(&"?").to_string(),
        }
    }

    /// Takes everything new from the bus. Returns true when the drive has ended.
    fn pull(&mut self, a: &Attached) -> Result<bool> {
        while let Some(e) = a.try_event()? {
            self.log_event(e);
        }
        let mut end = false;
        while let Some(v) = a.try_view()? {
            if self.view.is_none() {
                self.message = drivelab_runtime::rt::keep_off(v.rt_cores, "monitor");
            }
            end |= self.show(v);
        }
        Ok(end)
    }

    /// Keeps a supervisor event unless it is not newer than the last one kept (a history
    /// resent to a late subscriber); the oldest go beyond [`LOG_KEEP`].
    fn log_event(&mut self, e: EventEntry) {
        if self.events.back().is_none_or(|b| e.seq > b.seq) {
            if self.events.len() == LOG_KEEP {
                self.events.pop_front();
            }
            self.events.push_back(e);
        }
    }

    /// Shows view `v`; true when it is the drive's last.
    fn show(&mut self, v: DriveView) -> bool {
        let end = v.hdr.is_end();
        self.view = Some(Box::new(v));
        end
    }

    /// Handles one key; returns false to quit.
    fn key(&mut self, code: KeyCode, mods: KeyModifiers, a: Option<&Attached>) -> Result<bool> {
        if code == KeyCode::Char('c') && mods.contains(KeyModifiers::CONTROL) {
            return Ok(false);
        }
        if let Some(kind) = self.confirm.take() {
            if code == KeyCode::Char('y') {
                self.message = self.request(kind, a)?;
            } else {
                self.message = "cancelled".into();
            }
            return Ok(true);
        }
        match code {
            KeyCode::Char('q') | KeyCode::Esc => return Ok(false),
            KeyCode::Right | KeyCode::Down | KeyCode::Tab => {
                self.selected = (self.selected + 1) % self.n_stages()
            }
            KeyCode::Left | KeyCode::Up | KeyCode::BackTab => {
                self.selected = (self.selected + self.n_stages() - 1) % self.n_stages()
            }
            KeyCode::Char(c @ '1'..='8') if (c as usize - '1' as usize) < self.n_stages() => {
                self.selected = c as usize - '1' as usize
            }
            KeyCode::Char('k') => self.ask(FAULT_KILL),
            KeyCode::Char('s') => self.ask(FAULT_STOP),
            _ => {}
        }
        Ok(true)
    }

    fn ask(&mut self, kind: u32) {
        if self.ended {
            self.message = "the drive has ended; no fault to inject".into();
        } else if self.view.as_ref().is_some_and(|v| v.lockstep != 0) {
            self.message = "faults need a real-time drive (this one runs in lockstep)".into();
        } else {
            self.confirm = Some(kind);
        }
    }

    fn fault_text(&self, kind: u32) -> String {
        let svc = self.stage_name(self.selected);
        if kind == FAULT_KILL {
            format!("kill {svc} (SIGKILL)")
        } else {
            format!(
                "freeze {svc} for {} ms (SIGSTOP, then SIGCONT)",
                self.stop_ms
            )
        }
    }

    fn request(&self, kind: u32, a: Option<&Attached>) -> Result<String> {
        let Some(a) = a else {
            return Ok("not attached".into());
        };
        let sent = a.send(&FaultRequest {
            kind,
            service: self.selected as u32,
            stop_ms: self.stop_ms,
            pid: std::process::id(),
        });
        Ok(match sent {
            Ok(()) => format!("asked the supervisor to {}", self.fault_text(kind)),
            // A remote drive's refusal is shown, not fatal.
            Err(e) => format!("{e:#}"),
        })
    }

    fn draw(&self, f: &mut Frame) {
        // The stage table whole first (a row per stage, its header and borders), then the
        // charts and the event log share what is left: the log 8 rows where the charts keep
        // 8, else half of it.
        let table_rows = self.n_stages() as u16 + 3;
        let rest = f.area().height.saturating_sub(table_rows + 3);
        let log_rows = if rest >= 16 { 8 } else { rest / 2 };
        let [head, table, cycle, charts, log, foot] = Layout::vertical([
            Constraint::Length(1),
            Constraint::Length(table_rows),
            Constraint::Length(1),
            Constraint::Min(0),
            Constraint::Length(log_rows),
            Constraint::Length(1),
        ])
        .areas(f.area());
        f.render_widget(Paragraph::new(self.header()), head);
        self.draw_table(f, table);
        f.render_widget(Paragraph::new(self.cycle_line()), cycle);
        let [left, right] =
            Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
                .areas(charts);
        self.draw_speed(f, left);
        self.draw_currents(f, right);
        self.draw_log(f, log);
        f.render_widget(Paragraph::new(self.footer()), foot);
    }

    fn header(&self) -> Line<'static> {
        let Some(v) = &self.view else {
            return Line::from(format!(
                "drivelab monitor · bus {} · waiting for the drive's first view…",
                self.bus
            ));
        };
        let k = v.hdr.k;
        let pct = if v.n_samples > 0 {
            100.0 * k as f64 / v.n_samples as f64
        } else {
            0.0
        };
        Line::from(vec![
            Span::styled(
                "drivelab monitor",
                Style::new().add_modifier(Modifier::BOLD),
            ),
            Span::raw(format!(
                " · bus {} · {} · {} {:.0} Hz · sample {}/{} ({:.0} %) · t {:.3} s{}",
                self.bus,
                get_str(&v.scenario),
                if v.lockstep != 0 {
                    "lockstep"
                } else {
                    "realtime"
                },
                v.sample_hz,
                k,
                v.n_samples,
                pct,
                k as f64 / v.sample_hz.max(1.0),
                if self.ended { " · ENDED" } else { "" }
            )),
        ])
    }

    fn draw_table(&self, f: &mut Frame, area: Rect) {
        let us = |ns: u64| format!("{:.1}", ns as f64 * 1e-3);
        let names: Vec<String> = (0..self.n_stages()).map(|i| self.stage_name(i)).collect();
        let rows = names.iter().enumerate().map(|(i, name)| {
            let mark = if i == self.selected { "▶ " } else { "  " };
            let Some(v) = &self.view else {
                return Row::new(vec![Cell::from(format!("{mark}{name}"))]);
            };
            let s = &v.services[i];
            let st = ProcState::from_u32(s.state);
            let color = match st {
                ProcState::Alive => Color::Green,
                ProcState::Finished => Color::Blue,
                ProcState::Frozen | ProcState::Restarting | ProcState::Starting => Color::Yellow,
                ProcState::Dead => Color::Red,
            };
            let x = &s.status;
            let mut cells = vec![
                Cell::from(format!("{mark}{name}")),
                Cell::from(st.name()).style(Style::new().fg(color)),
                Cell::from(s.pid.to_string()),
                Cell::from(s.restarts.to_string()),
            ];
            if s.has_status != 0 {
                cells.extend([
                    Cell::from(format!("{:.2}", s.rate_hz * 1e-3)),
                    Cell::from(us(x.wake.quantile_ns(0.99))),
                    Cell::from(us(x.wake.max_ns)),
                    Cell::from(us(x.exec.quantile_ns(0.99))),
                    Cell::from(us(x.exec.max_ns)),
                    Cell::from(format!("{} ({})", x.misses, x.longest_miss_run)),
                    Cell::from(x.stale_inputs.to_string()),
                    Cell::from(x.rejected_inputs.to_string()),
                ]);
            } else {
                // No status yet: every figure a dash (the title says so).
                cells.extend(std::iter::repeat_n(Cell::from(NO_STATUS), 8));
            }
            let row = Row::new(cells);
            if i == self.selected {
                row.style(Style::new().add_modifier(Modifier::REVERSED))
            } else {
                row
            }
        });
        let header = Row::new([
            "stage",
            "state",
            "pid",
            "restarts",
            "kHz",
            "wake p99",
            "wake max",
            "exec p99",
            "exec max",
            "misses (run)",
            "stale",
            "rejected",
        ])
        .style(Style::new().add_modifier(Modifier::BOLD));
        let widths = [
            // The stage's name whole; the figures give way on a narrow screen.
            Constraint::Min(14),
            Constraint::Length(10),
            Constraint::Length(7),
            Constraint::Length(8),
            Constraint::Length(6),
            Constraint::Length(8),
            Constraint::Length(8),
            Constraint::Length(8),
            Constraint::Length(8),
            Constraint::Length(12),
            Constraint::Length(6),
            Constraint::Length(8),
            // What a wide screen has left over.
            Constraint::Fill(1),
        ];
        f.render_widget(
            Table::new(rows, widths)
                .header(header)
                .block(Block::bordered().title(format!(
                    " stages · µs, since start · wake: plant = timer lateness, others = bus hop · {NO_STATUS} no status yet "
                ))),
            area,
        );
    }

    fn cycle_line(&self) -> Line<'static> {
        let Some(v) = &self.view else {
            return Line::default();
        };
        let p = &v.services[0].status;
        if v.lockstep != 0 {
            return Line::from(" cycle latency: not measured in lockstep (no wall-clock schedule)");
        }
        Line::from(format!(
            " cycle t_k → command k at the plant: p99 {:.1} µs, max {:.1} µs · deadline misses {}/{} samples, longest run {}",
            p.cycle.quantile_ns(0.99) as f64 * 1e-3,
            p.cycle.max_ns as f64 * 1e-3,
            p.misses,
            p.samples,
            p.longest_miss_run
        ))
    }

    fn series(&self, pick: impl Fn(&TracePoint) -> f64) -> Vec<(f64, f64)> {
        let Some(v) = &self.view else {
            return Vec::new();
        };
        v.points[..v.n_points as usize]
            .iter()
            .map(|p| (p.k as f64 / v.sample_hz.max(1.0), pick(p)))
            .collect()
    }

    fn chart(&self, f: &mut Frame, area: Rect, title: String, unit: &str, sets: Vec<Series<'_>>) {
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for (_, _, d) in &sets {
            for &(x, y) in d {
                x0 = x0.min(x);
                x1 = x1.max(x);
                y0 = y0.min(y);
                y1 = y1.max(y);
            }
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        // A flat trace keeps a visible band (5 % of its level) instead of magnifying noise.
        let pad = ((y1 - y0) * 0.1)
            .max(0.05 * y0.abs().max(y1.abs()))
            .max(1e-3);
        let (y0, y1) = (y0 - pad, y1 + pad);
        let datasets = sets
            .iter()
            .map(|(name, color, d)| {
                Dataset::default()
                    .name(name.to_string())
                    .marker(Marker::Braille)
                    .graph_type(GraphType::Line)
                    .style(Style::new().fg(*color))
                    .data(d)
            })
            .collect::<Vec<_>>();
        let chart = Chart::new(datasets)
            .block(Block::bordered().title(title))
            .legend_position(Some(ratatui::widgets::LegendPosition::BottomRight))
            .x_axis(
                Axis::default()
                    .title("t s")
                    .bounds([x0, x1.max(x0 + 1e-6)])
                    .labels([format!("{x0:.2}"), format!("{x1:.2}")]),
            )
            .y_axis(
                Axis::default()
                    .title(unit.to_string())
                    .bounds([y0, y1])
                    .labels([format!("{y0:.1}"), format!("{y1:.1}")]),
            );
        f.render_widget(chart, area);
    }

    fn last_point(&self) -> Option<TracePoint> {
        self.view
            .as_ref()
            .and_then(|v| v.points[..v.n_points as usize].last().copied())
    }

    fn draw_speed(&self, f: &mut Frame, area: Rect) {
        let title = match self.last_point() {
            Some(p) => format!(
                " speed ω {:.2} rad/s, reference ω* {:.2} rad/s ",
                p.omega, p.omega_ref
            ),
            None => " speed ω and reference ω* ".into(),
        };
        let sets = vec![
            ("ω*", Color::Yellow, self.series(|p| p.omega_ref)),
            ("ω", Color::Cyan, self.series(|p| p.omega)),
        ];
        self.chart(f, area, title, "rad/s", sets);
    }

    fn draw_currents(&self, f: &mut Frame, area: Rect) {
        let title = match self.last_point() {
            Some(p) => format!(
                " currents i_d {:.3} A (i_d* {:.3}), i_q {:.3} A (i_q* {:.3}) ",
                p.i_d, p.i_d_ref, p.i_q, p.i_q_ref
            ),
            None => " currents i_d and i_q ".into(),
        };
        let sets = vec![
            ("i_q*", Color::Yellow, self.series(|p| p.i_q_ref)),
            ("i_d*", Color::LightRed, self.series(|p| p.i_d_ref)),
            ("i_q", Color::Cyan, self.series(|p| p.i_q)),
            ("i_d", Color::Magenta, self.series(|p| p.i_d)),
        ];
        self.chart(f, area, title, "A", sets);
    }

    fn draw_log(&self, f: &mut Frame, area: Rect) {
        let fs = self.view.as_ref().map_or(1.0, |v| v.sample_hz.max(1.0));
        let shown = area.height.saturating_sub(2) as usize;
        let lines: Vec<Line> = if self.events.is_empty() {
            vec![Line::from(
                "no events: every service running since the start",
            )]
        } else {
            self.events
                .iter()
                .rev()
                .take(shown)
                .rev()
                .map(|e| {
                    let red = e.text().starts_with("inject") || e.text().starts_with("exited");
                    Line::styled(
                        format!(
                            "wall {:8.3} s  sample {:>8} (t {:.4} s)  {}",
                            e.t_wall_s,
                            e.k,
                            e.k as f64 / fs,
                            e.text()
                        ),
                        if red {
                            Style::new().fg(Color::Red)
                        } else {
                            Style::new()
                        },
                    )
                })
                .collect()
        };
        f.render_widget(
            Paragraph::new(lines).block(Block::bordered().title(format!(
                " supervisor events ({} so far) ",
                self.events.back().map_or(0, |e| e.seq + 1)
            ))),
            area,
        );
    }

    fn footer(&self) -> Line<'static> {
        if let Some(kind) = self.confirm {
            return Line::styled(
                format!(
                    " {}? press y to confirm, any other key to cancel",
                    self.fault_text(kind)
                ),
                Style::new().fg(Color::Black).bg(Color::Yellow),
            );
        }
        let keys = format!(
            " q quit · ←/→ or 1-{} select ({}) · k kill · s freeze {} ms",
            self.n_stages(),
            self.stage_name(self.selected),
            self.stop_ms
        );
        if self.message.is_empty() {
            Line::from(keys)
        } else {
            Line::from(format!("{keys} · {}", self.message))
        }
    }
}

/// Without the terminal UI (the cross build): says so in one line.
#[cfg(not(feature = "tui"))]
pub fn run(_: &MonitorOptions) -> Result<()> {
    bail!(
        "this drivelab was built without the monitor's terminal UI (cargo feature `tui`, off \
         in the cross build); rebuild with it: scripts/cross.sh TARGET --features tui"
    )
}

#[cfg(feature = "tui")]
/// Runs `drivelab monitor`.
pub fn run(o: &MonitorOptions) -> Result<()> {
    if o.stop_ms == 0 || o.stop_ms > 60_000 {
        // The command line bounds it first (clap); a library caller gets the same usage error.
        return Err(crate::expect::usage(format!(
            "--stop-ms {} is out of range (1..60000 ms)",
            o.stop_ms
        )));
    }
    let attached = attach(&o.target)?;
    let mut ui = Ui::new(o);
    ui.bus = attached.label(&o.target);
    if let Some((w, h)) = o.print {
        return print_once(&mut ui, attached, w, h);
    }
    // SAFETY: isatty only reads the file descriptor's state.
    if unsafe { libc::isatty(1) } != 1 {
        bail!("monitor needs a terminal on stdout; use --print for a one-shot text view");
    }
    let mut terminal = ratatui::try_init().context("cannot set up the terminal")?;
    let result = ui_loop(&mut terminal, &mut ui, attached, o.refresh);
    ratatui::restore();
    result
}

#[cfg(feature = "tui")]
fn ui_loop(
    terminal: &mut ratatui::DefaultTerminal,
    ui: &mut Ui,
    attached: Attached,
    refresh: Duration,
) -> Result<()> {
    let mut attached = Some(attached);
    loop {
        if let Some(a) = &attached {
            if ui.pull(a)? {
                // Let go of the bus at once so the launcher can remove its files.
                ui.ended = true;
                ui.message = "the drive has ended: press q to leave".into();
                attached = None;
            }
        }
        terminal.draw(|f| ui.draw(f))?;
        let until = Instant::now() + refresh;
        while let Some(left) = until.checked_duration_since(Instant::now()) {
            if crate::common::stop_requested() {
                return Ok(());
            }
            if !event::poll(left.min(Duration::from_millis(50)))? {
                continue;
            }
            if let Event::Key(k) = event::read()? {
                if k.kind == KeyEventKind::Press
                    && !ui.key(k.code, k.modifiers, attached.as_ref())?
                {
                    return Ok(());
                }
                break;
            }
        }
    }
}

#[cfg(feature = "tui")]
fn print_once(ui: &mut Ui, a: Attached, w: u16, h: u16) -> Result<()> {
    use ratatui::backend::TestBackend;
    let t = Instant::now();
    while ui.view.is_none() && t.elapsed() < Duration::from_secs(5) {
        ui.ended |= ui.pull(&a)?;
        std::thread::sleep(Duration::from_millis(20));
    }
    ui.ended |= ui.pull(&a)?;
    drop(a);
    if ui.view.is_none() {
        bail!("the drive on bus '{}' published no view within 5 s", ui.bus);
    }
    let mut term = ratatui::Terminal::new(TestBackend::new(w, h))?;
    term.draw(|f| ui.draw(f))?;
    let buf = term.backend().buffer();
    let mut out = String::new();
    for y in 0..buf.area.height {
        let mut line = String::new();
        for x in 0..buf.area.width {
            line.push_str(buf[(x, y)].symbol());
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    crate::out!("{out}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use ratatui::backend::TestBackend;

    fn ui() -> Ui {
        Ui::new(&MonitorOptions {
            target: Target::Bus("b1".into()),
            refresh: Duration::from_millis(100),
            stop_ms: 20,
            print: None,
        })
    }

    /// A view of a four-stage drive at sample `k` of 1000 (10 kHz); every stage alive with
    /// a status except the last; the plant's cycle at 30 µs with 2 misses.
    fn view(k: u64, lockstep: bool) -> DriveView {
        let mut v = DriveView {
            sample_hz: 10_000.0,
            n_samples: 1000,
            lockstep: u32::from(lockstep),
            n_stages: 4,
            ..Default::default()
        };
        v.hdr.k = k;
        put_str(&mut v.scenario, "kyslan-pi");
        for (i, name) in ["plant", "observer", "current-loop", "speed-loop"]
            .iter()
            .enumerate()
        {
            put_str(&mut v.stage_names[i], name);
            v.services[i].state = ProcState::Alive as u32;
            v.services[i].pid = 100 + i as u32;
            v.services[i].has_status = u32::from(i < 3);
        }
        let p = &mut v.services[0].status;
        (p.misses, p.samples, p.longest_miss_run) = (2, k, 1);
        p.cycle.record_ns(30_000);
        v
    }

    fn press(u: &mut Ui, keys: &str) -> bool {
        keys.chars()
            .all(|c| u.key(KeyCode::Char(c), KeyModifiers::NONE, None).unwrap())
    }

    /// The screen as text.
    fn screen(u: &Ui) -> String {
        screen_of(u, 150, 45)
    }

    /// The screen of `w` × `h` cells as text.
    fn screen_of(u: &Ui, w: u16, h: u16) -> String {
        let mut term = ratatui::Terminal::new(TestBackend::new(w, h)).unwrap();
        term.draw(|f| u.draw(f)).unwrap();
        let buf = term.backend().buffer();
        (0..buf.area.height)
            .map(|y| {
                (0..buf.area.width)
                    .map(|x| buf[(x, y)].symbol())
                    .collect::<String>()
            })
            .collect::<Vec<_>>()
            .join("\n")
    }

    #[test]
    fn the_smallest_screen_shows_every_stage() {
        let mut u = ui();
        u.show(view(10, false));
        // 20 rows, the fewest --print-size takes: every stage's row, the cycle line and the
        // footer, with the charts and the log in what is left.
        for (w, h) in [(100, 20), (40, 20), (150, 45)] {
            let text = screen_of(&u, w, h);
            let lines: Vec<&str> = text.lines().collect();
            for name in ["plant", "observer", "current-loop", "speed-loop"] {
                assert!(
                    lines
                        .iter()
                        .any(|l| l.contains(&format!("  {name} "))
                            || l.contains(&format!("▶ {name} "))),
                    "{w}x{h}: no {name} row:\n{text}"
                );
            }
            assert!(lines[8].contains("cycle"), "{w}x{h}:\n{text}");
        }
    }

    #[test]
    fn keys_select_stages_within_the_drive_and_quit() {
        let mut u = ui();
        assert!(!u.show(view(10, false)));
        // Arrows wrap both ways; a digit selects only a stage that exists.
        u.key(KeyCode::Left, KeyModifiers::NONE, None).unwrap();
        assert_eq!(u.selected, 3);
        u.key(KeyCode::Right, KeyModifiers::NONE, None).unwrap();
        assert_eq!(u.selected, 0);
        assert!(press(&mut u, "3"));
        assert_eq!(u.stage_name(u.selected), "current-loop");
        assert!(press(&mut u, "5"));
        assert_eq!(u.selected, 2);
        assert!(!press(&mut u, "q"));
        assert!(!u.key(KeyCode::Esc, KeyModifiers::NONE, None).unwrap());
        assert!(!u
            .key(KeyCode::Char('c'), KeyModifiers::CONTROL, None)
            .unwrap());
    }

    #[test]
    fn a_fault_is_asked_confirmed_or_cancelled_and_refused_in_lockstep_or_after_the_end() {
        let mut u = ui();
        u.show(view(10, false));
        press(&mut u, "2k");
        assert!(
            screen(&u).contains("kill observer (SIGKILL)? press y to confirm"),
            "{}",
            screen(&u)
        );
        press(&mut u, "n");
        assert_eq!((u.confirm, u.message.as_str()), (None, "cancelled"));
        // A stop names its duration; confirmed without a bus, nothing is sent.
        press(&mut u, "s");
        assert_eq!(u.confirm, Some(FAULT_STOP));
        assert!(screen(&u).contains("freeze observer for 20 ms (SIGSTOP, then SIGCONT)?"));
        press(&mut u, "y");
        assert_eq!((u.confirm, u.message.as_str()), (None, "not attached"));
        // Lockstep: refused at once, no confirmation asked.
        u.show(view(10, true));
        press(&mut u, "k");
        assert_eq!(u.confirm, None);
        assert_eq!(
            u.message,
            "faults need a real-time drive (this one runs in lockstep)"
        );
        u.ended = true;
        press(&mut u, "s");
        assert_eq!(
            (u.confirm, u.message.as_str()),
            (None, "the drive has ended; no fault to inject")
        );
    }

    #[test]
    fn the_event_log_keeps_new_events_only_and_the_last_200() {
        let mut u = ui();
        for seq in [0, 1, 1, 0, 2] {
            u.log_event(EventEntry::new(0.1, 5, seq, "inject plant: kill"));
        }
        assert_eq!(
            u.events.iter().map(|e| e.seq).collect::<Vec<_>>(),
            [0, 1, 2]
        );
        for seq in 3..=LOG_KEEP as u64 + 9 {
            u.log_event(EventEntry::new(0.1, 5, seq, "resume observer: SIGCONT"));
        }
        assert_eq!(u.events.len(), LOG_KEEP);
        assert_eq!(u.events.front().unwrap().seq, 10);
        // The log's title counts every event the supervisor logged.
        u.show(view(10, false));
        assert!(screen(&u).contains("supervisor events (210 so far)"));
    }

    #[test]
    fn the_screen_shows_progress_states_the_plants_cycle_and_the_end() {
        let mut u = ui();
        assert!(screen(&u).contains("waiting for the drive's first view"));
        assert!(screen(&u).contains("no events: every service running since the start"));
        u.log_event(EventEntry::new(
            1.25,
            500,
            0,
            "exited current-loop: signal: 9",
        ));
        u.show(view(500, false));
        let s = screen(&u);
        for want in [
            "bus b1 · kyslan-pi · realtime 10000 Hz · sample 500/1000 (50 %) · t 0.050 s",
            "deadline misses 2/500 samples, longest run 1",
            "wall    1.250 s  sample      500 (t 0.0500 s)  exited current-loop",
        ] {
            assert!(s.contains(want), "{want}\n{s}");
        }
        // Four stages alive; three with a status, the fourth without one yet.
        let rows: Vec<&str> = s.lines().filter(|l| l.contains(" alive ")).collect();
        assert_eq!(rows.len(), 4, "{s}");
        let dashes = |l: &str| l.split_whitespace().filter(|w| *w == NO_STATUS).count();
        assert_eq!(
            rows.iter().map(|l| dashes(l)).collect::<Vec<_>>(),
            [0, 0, 0, 8]
        );
        assert!(rows[0].contains(" 2 (1) "), "{}", rows[0]);
        // The drive's last view ends it.
        let mut last = view(1000, true);
        last.hdr.flags |= drivelab_runtime::messages::FLAG_END;
        assert!(u.show(last));
        u.ended = true;
        let s = screen(&u);
        assert!(
            s.contains("lockstep 10000 Hz · sample 1000/1000 (100 %)"),
            "{s}"
        );
        assert!(s.contains("· ENDED"), "{s}");
        assert!(s.contains("cycle latency: not measured in lockstep"), "{s}");
    }

    /// `e` is a usage error (exit 2) that reads `text`.
    fn assert_usage_error(e: anyhow::Error, text: &str) {
        assert!(
            e.is::<crate::expect::UsageError>(),
            "{e}: not a usage error"
        );
        assert_eq!(e.to_string(), text);
    }

    #[test]
    fn a_fault_request_with_a_stop_out_of_range_is_a_usage_error_before_attaching() {
        for stop_ms in [0, 60_001] {
            let target = Target::Bus("no-such-bus".into());
            assert_usage_error(
                request_fault(&target, FAULT_STOP, "plant", stop_ms).unwrap_err(),
                &format!("a stop lasts 1 ms to 60 s, not {stop_ms} ms"),
            );
        }
    }

    #[test]
    fn a_stop_beyond_a_minute_or_of_nothing_is_refused_before_attaching() {
        for stop_ms in [0, 60_001] {
            let o = MonitorOptions {
                target: Target::Bus("no-such-bus".into()),
                refresh: Duration::from_millis(100),
                stop_ms,
                print: None,
            };
            assert_usage_error(
                run(&o).unwrap_err(),
                &format!("--stop-ms {stop_ms} is out of range (1..60000 ms)"),
            );
        }
    }
}
