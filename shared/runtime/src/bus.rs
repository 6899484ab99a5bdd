//! iceoryx2 helpers: an isolated bus per run (its own file prefix and root path), the
//! four topics, and their wake-up events.
//!
//! Files of bus `ID` live in `/dev/shm/iox2_dl<ID>_*` and `/tmp/iceoryx2/dl<ID>/`; [`cleanup`]
//! removes both, so that tests can run side by side and leave nothing behind.

use crate::futex::WakeSegment;
use anyhow::{anyhow, Context, Result};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample_mut_uninit::SampleMutUninit;
use std::sync::Arc;
use std::time::Duration;

/// Topics of the drive.
pub const TOPIC_MEAS: &str = "drivelab/meas";
/// Estimates.
pub const TOPIC_EST: &str = "drivelab/est";
/// Current references.
pub const TOPIC_IREF: &str = "drivelab/iref";
/// Voltage commands.
pub const TOPIC_CMD: &str = "drivelab/cmd";
/// Speed references of an outer loop (e.g. a position loop).
pub const TOPIC_WREF: &str = "drivelab/wref";
/// The plant's true state, for the recorder only.
pub const TOPIC_TRUTH: &str = "drivelab/truth";
/// Recorder progress (lockstep flow control).
pub const TOPIC_REC: &str = "drivelab/recorder";

/// Longest sleep of a polled receiver's [`Receiver::wait`].
pub const POLL_SLEEP: Duration = Duration::from_micros(200);

/// Largest subscriber buffer (the recorder's), samples.
pub const MAX_BUFFER: usize = 4096;
/// Samples kept for late joiners (publisher history).
pub const HISTORY: usize = 256;
/// Subscribers per topic: the stage hosts that read it, their standby twins (each also
/// watches its own outputs), the recorder and a restarted host joining before its dead
/// predecessor's port is removed.
const MAX_SUBSCRIBERS: usize = 8;
/// Nodes per topic: the hosts, their twins, the launcher and the tools that attach.
const MAX_NODES: usize = 16;

/// Sets iceoryx2's own log to errors only, or to the level `IOX2_LOG_LEVEL` names (trace,
/// debug, info, warn, error, fatal) for debugging. Its warnings are details drivelab reports
/// in its own words, or noise: when two processes leave the bus at the same moment, one may
/// see the other's node half removed and say that it found no config file. The level is
/// process-wide; every `main` that uses the bus calls this first.
pub fn quiet_iceoryx2_log() {
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
}

/// What may keep a shared-memory segment from being made: a file size limit (`ulimit -f`)
/// or the free space of /dev/shm.
fn segment_limit() -> String {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit(2) writes only into `lim`, which outlives the call.
    let rc = unsafe { libc::getrlimit(libc::RLIMIT_FSIZE, &mut lim) };
    if rc == 0 && lim.rlim_cur != libc::RLIM_INFINITY {
        return format!(
            "the file size limit, ulimit -f, is {} KiB: raise it",
            lim.rlim_cur / 1024
        );
    }
    // SAFETY: an all-zero statvfs is a valid value for statvfs(2) to overwrite.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: the path is a NUL-terminated literal; statvfs(2) writes only into `st`.
    if unsafe { libc::statvfs(c"/dev/shm".as_ptr(), &mut st) } == 0 {
        let free = st.f_bavail as u64 * st.f_frsize as u64;
        return format!("{} MiB free there", free >> 20);
    }
    "full, or not writable".into()
}

/// Validates a bus id: 1–24 characters of [A-Za-z0-9_].
pub fn check_bus_id(id: &str) -> Result<()> {
    if id.is_empty() || id.len() > 24 || !id.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
    {
        return Err(anyhow!(
            "bus id '{id}' must be 1-24 characters of A-Z, a-z, 0-9 or _"
        ));
    }
    Ok(())
}

/// File prefix of bus `id` in /dev/shm.
pub fn shm_prefix(id: &str) -> String {
    format!("iox2_dl{id}_")
}

/// Root path of bus `id`.
pub fn root_path(id: &str) -> String {
    format!("/tmp/iceoryx2/dl{id}/")
}

/// iceoryx2 configuration of bus `id`.
pub fn config(id: &str) -> Result<Config> {
    check_bus_id(id)?;
    let mut cfg = Config::default();
    cfg.global.prefix =
        FileName::new(shm_prefix(id).as_bytes()).map_err(|e| anyhow!("bus prefix: {e:?}"))?;
    cfg.global.set_root_path(
        &Path::new(root_path(id).as_bytes()).map_err(|e| anyhow!("bus root path: {e:?}"))?,
    );
    Ok(cfg)
}

/// The iceoryx2 configuration of bus `id` as a TOML file, for iceoryx2's own tools: saved as
/// `config/iceoryx2.toml` in a run folder, it lets `iox2` find the drive's services when run
/// from that folder (iceoryx2 reads a project-local `config/iceoryx2.toml` first).
pub fn config_toml(id: &str) -> Result<String> {
    let cfg = config(id)?;
    toml::to_string(&cfg).map_err(|e| anyhow!("cannot write the iceoryx2 config of bus {id}: {e}"))
}

/// Checks that `path`, if it exists, is a real folder (not a symbolic link) owned by this
/// process's user; `lstat` does not follow a link.
fn check_folder(path: &std::path::Path) -> Result<bool> {
    use std::os::unix::fs::MetadataExt;
    // A trailing '/' would make lstat follow a link: inspect the entry itself.
    let path = std::path::Path::new(path.to_str().unwrap_or("").trim_end_matches('/'));
    let m = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
        Err(e) => return Err(anyhow!("cannot inspect {}: {e}", path.display())),
    };
    if m.file_type().is_symlink() {
        let to = std::fs::read_link(path)
            .map(|t| t.display().to_string())
            .unwrap_or_default();
        return Err(anyhow!(
            "bus folder {} is a symbolic link (to {to}); refusing to use it: remove the link by hand",
            path.display()
        ));
    }
    if !m.is_dir() {
        return Err(anyhow!("bus folder {} is not a folder", path.display()));
    }
    // SAFETY: geteuid(2) has no arguments and cannot fail.
    let me = unsafe { libc::geteuid() };
    if m.uid() != me {
        return Err(anyhow!(
            "bus folder {} belongs to uid {}, not to this user (uid {me}); refusing to use it: \
             that user's drive owns this bus (give another --bus, or as that user, once its \
             drive is gone, `drivelab clean`)",
            path.display(),
            m.uid()
        ));
    }
    Ok(true)
}

/// Makes the root folder of bus `id` (mode 0700, owned by this user) if it is missing, and
/// refuses one that is a symbolic link or belongs to another user.
pub fn prepare_root(id: &str) -> Result<()> {
    use std::os::unix::fs::{DirBuilderExt, PermissionsExt};
    check_bus_id(id)?;
    let root = root_path(id);
    let root = std::path::Path::new(root.trim_end_matches('/'));
    let parent = root.parent().unwrap_or(std::path::Path::new("/tmp"));
    // The shared parent (iceoryx2's default root) may belong to anyone, but must not be a link.
    if let Ok(m) = std::fs::symlink_metadata(parent) {
        if m.file_type().is_symlink() {
            return Err(anyhow!(
                "{} is a symbolic link; refusing to make bus folders through it",
                parent.display()
            ));
        }
        use std::os::unix::fs::MetadataExt;
        // SAFETY: geteuid has no preconditions and cannot fail.
        let me = unsafe { libc::geteuid() };
        check_shared_owner(parent, m.uid(), me)?;
    } else {
        // Shared by every user's buses, as /tmp is: anyone may make a folder in it, only its
        // owner may remove it (sticky). The umask would narrow the mode given at creation.
        match std::fs::create_dir(parent) {
            Ok(()) => std::fs::set_permissions(parent, std::fs::Permissions::from_mode(0o1777))
                .with_context(|| format!("cannot set the mode of {}", parent.display()))?,
            // Made by another drive in the meantime.
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(anyhow!("cannot create {}: {e}", parent.display())),
        }
    }
    if check_folder(root)? {
        // Ours: make sure nobody else can enter it.
        std::fs::set_permissions(root, std::fs::Permissions::from_mode(0o700))
            .with_context(|| format!("cannot set the mode of {}", root.display()))?;
    } else {
        std::fs::DirBuilder::new()
            .mode(0o700)
            .create(root)
            .map_err(|e| {
                let shared = if e.kind() == std::io::ErrorKind::PermissionDenied {
                    format!(
                        " ({} is not open to this user: its owner can open it to every user with `chmod 1777 {}`)",
                        parent.display(),
                        parent.display()
                    )
                } else {
                    String::new()
                };
                anyhow!("cannot create bus folder {}: {e}{shared}", root.display())
            })?;
        check_folder(root)?;
    }
    Ok(())
}

/// The shared parent of the bus folders must belong to root or to this user (`me`): the
/// owner of a sticky folder may rename or remove any folder in it, so another user who owns
/// it could swap a bus folder for one of theirs.
fn check_shared_owner(parent: &std::path::Path, owner: u32, me: u32) -> Result<()> {
    if owner == 0 || owner == me {
        return Ok(());
    }
    Err(anyhow!(
        "{} belongs to uid {owner}, neither root nor this user (uid {me}): its owner could replace this user's bus folders; as root, remove it (drivelab makes it again) or `chown root {}`",
        parent.display(),
        parent.display()
    ))
}

/// Names of the live iceoryx2 nodes of bus `id` (none when the bus has no folder).
pub fn live_nodes(id: &str) -> Result<Vec<String>> {
    use iceoryx2::node::NodeView;
    let root = root_path(id);
    if !check_folder(std::path::Path::new(&root))? {
        return Ok(Vec::new());
    }
    let cfg = config(id)?;
    let mut alive = Vec::new();
    Node::<ipc::Service>::list(&cfg, |state| {
        if let NodeState::Alive(view) = state {
            alive.push(
                view.details()
                    .as_ref()
                    .map(|d| d.name().to_string())
                    .unwrap_or_else(|| "?".into()),
            );
        }
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow!("cannot list the nodes of bus {id}: {e:?}"))?;
    Ok(alive)
}

/// A node on bus `id`. Signals are handled by the caller (see `services`).
pub fn node(id: &str, name: &str) -> Result<Node<ipc::Service>> {
    prepare_root(id)?;
    let cfg = config(id)?;
    NodeBuilder::new()
        .config(&cfg)
        .name(&NodeName::new(name).map_err(|e| anyhow!("node name: {e:?}"))?)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| anyhow!("cannot create iceoryx2 node '{name}' on bus {id}: {e:?}"))
}

fn service_name(topic: &str) -> Result<ServiceName> {
    ServiceName::new(topic).map_err(|e| anyhow!("service name {topic}: {e:?}"))
}

/// How a sender wakes its receivers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum WakeKind {
    /// iceoryx2 event service (notifier/listener, a Unix datagram socket underneath).
    #[default]
    Iceoryx2,
    /// A futex word per topic in a shared segment of the bus (see [`crate::futex`]).
    Futex,
}

/// The wake-up side of a topic.
enum Wake {
    Event(iceoryx2::service::port_factory::event::PortFactory<ipc::Service>),
    Futex(Arc<WakeSegment>, usize),
}

/// Offset of a topic's decimated wake word from its own (see [`Topic::decimated_receiver`]).
pub const DECIMATED: usize = 8;
const _: () = assert!(2 * DECIMATED <= crate::futex::WORDS);

/// A typed topic: publish-subscribe plus a wake-up channel.
pub struct Topic<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> {
    /// The publish-subscribe service.
    pub pubsub:
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>,
    wake: Wake,
}

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> Topic<T> {
    /// Opens or creates the topic with an iceoryx2 event for wake-ups.
    pub fn open(node: &Node<ipc::Service>, topic: &str) -> Result<Self> {
        Self::open_with(node, topic, None)
    }

    /// Opens or creates the topic; wake-ups through `futex` word `i` if given, else an
    /// iceoryx2 event of the same name.
    pub fn open_with(
        node: &Node<ipc::Service>,
        topic: &str,
        futex: Option<(Arc<WakeSegment>, usize)>,
    ) -> Result<Self> {
        Self::open_shared(node, topic, futex, 1)
    }

    /// [`Topic::open_with`] for a topic with `publishers` publishers: 1, the stage that owns
    /// it, or 2 in a drive with standby twins (the twin's publisher is made at its set-up).
    /// Opening a topic that exists takes its own number (it must be at least this).
    pub fn open_shared(
        node: &Node<ipc::Service>,
        topic: &str,
        futex: Option<(Arc<WakeSegment>, usize)>,
        publishers: usize,
    ) -> Result<Self> {
        let name = service_name(topic)?;
        let pubsub = node
            .service_builder(&name)
            .publish_subscribe::<T>()
            // One publisher per topic: the stage that owns it (and its twin). A further
            // process on the same account cannot publish here (see docs/architecture.md,
            // "Who can reach a drive").
            .max_publishers(publishers)
            .max_subscribers(MAX_SUBSCRIBERS)
            .max_nodes(MAX_NODES)
            .subscriber_max_buffer_size(MAX_BUFFER)
            .history_size(HISTORY)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(|e| anyhow!("cannot open topic {topic}: {e:?}"))?;
        let wake = match futex {
            Some((seg, i)) => Wake::Futex(seg, i),
            None => Wake::Event(
                node.service_builder(&name)
                    .event()
                    .max_notifiers(4)
                    .max_listeners(8)
                    .max_nodes(MAX_NODES)
                    .open_or_create()
                    .map_err(|e| anyhow!("cannot open event {topic}: {e:?}"))?,
            ),
        };
        Ok(Self { pubsub, wake })
    }

    /// A sender (publisher + wake-up). Fails while another process publishes on the topic:
    /// every topic has exactly one publisher.
    pub fn sender(&self) -> Result<Sender<T>> {
        let notify = match &self.wake {
            Wake::Event(ev) => Notify::Event(Box::new(
                ev.notifier_builder()
                    .create()
                    .map_err(|e| anyhow!("notifier: {e:?}"))?,
            )),
            Wake::Futex(seg, i) => Notify::Futex(seg.clone(), *i),
        };
        Ok(Sender {
            publisher: self
                .pubsub
                .publisher_builder()
                .max_loaned_samples(2)
                .create()
                .map_err(|e| match e {
                    iceoryx2::port::publisher::PublisherCreateError::ExceedsMaxSupportedPublishers => anyhow!(
                        "topic {} already has its one publisher (another process owns it)",
                        self.pubsub.name()
                    ),
                    iceoryx2::port::publisher::PublisherCreateError::UnableToCreateDataSegment => anyhow!(
                        "topic {}: cannot make its data segment in /dev/shm ({})",
                        self.pubsub.name(),
                        segment_limit()
                    ),
                    e => anyhow!("publisher: {e:?}"),
                })?,
            notify,
            spare: std::cell::Cell::new(None),
        })
    }

    /// A wake-up without a message: consumers of this topic wake and check their inputs'
    /// freshness (the plant pokes the estimate topic when a command is missing, so that a
    /// controller whose producer died notices without a timer of its own).
    pub fn poker(&self) -> Result<Poker> {
        Ok(Poker(match &self.wake {
            Wake::Event(ev) => Notify::Event(Box::new(
                ev.notifier_builder()
                    .create()
                    .map_err(|e| anyhow!("notifier: {e:?}"))?,
            )),
            Wake::Futex(seg, i) => Notify::Futex(seg.clone(), *i),
        }))
    }

    /// A receiver with a buffer of `buffer` samples that can wait for the topic's wake-up.
    /// An iceoryx2 listener costs the sender one syscall per message, so inputs that are
    /// only polled should use [`Topic::polled_receiver`].
    pub fn receiver(&self, buffer: usize) -> Result<Receiver<T>> {
        let waiter = match &self.wake {
            Wake::Event(ev) => Waiter::Event(Box::new(
                ev.listener_builder()
                    .create()
                    .map_err(|e| anyhow!("listener: {e:?}"))?,
            )),
            Wake::Futex(seg, i) => {
                Waiter::Futex(seg.clone(), *i, std::cell::Cell::new(seg.seq(*i)))
            }
        };
        Ok(Receiver {
            subscriber: self.subscriber(buffer)?,
            waiter,
        })
    }

    /// Like [`Topic::receiver`], but woken only by the sends that ask for it
    /// ([`Sender::send_waking`]) and by pokes: a stage that steps at a fraction of its
    /// trigger's rate sleeps through the samples it does not step. Iceoryx2 events have no
    /// such channel: with them this is [`Topic::receiver`].
    pub fn decimated_receiver(&self, buffer: usize) -> Result<Receiver<T>> {
        let Wake::Futex(seg, i) = &self.wake else {
            return self.receiver(buffer);
        };
        let w = i + DECIMATED;
        Ok(Receiver {
            subscriber: self.subscriber(buffer)?,
            waiter: Waiter::Futex(seg.clone(), w, std::cell::Cell::new(seg.seq(w))),
        })
    }

    /// How many wake-ups this topic has had: its futex wake word, which every
    /// [`Sender::send_waking`] (markers included) and every poke bumps once, wrapping at
    /// 2^32. None with iceoryx2 events, which keep no count. The launcher reads the plant's
    /// count to know how far the plant really is, where its schedule would only say how far
    /// it should be.
    pub fn publish_count(&self) -> Option<PublishCount> {
        match &self.wake {
            Wake::Futex(seg, i) => Some(PublishCount(seg.clone(), *i)),
            Wake::Event(_) => None,
        }
    }

    /// A receiver that is only polled (the sender does not wake it).
    pub fn polled_receiver(&self, buffer: usize) -> Result<Receiver<T>> {
        Ok(Receiver {
            subscriber: self.subscriber(buffer)?,
            waiter: Waiter::Polled,
        })
    }

    fn subscriber(&self, buffer: usize) -> Result<Subscriber<ipc::Service, T, ()>> {
        self.pubsub
            .subscriber_builder()
            .buffer_size(buffer.min(MAX_BUFFER))
            .create()
            .map_err(|e| anyhow!("subscriber: {e:?}"))
    }
}

/// A topic's wake count (see [`Topic::publish_count`]).
#[derive(Debug, Clone)]
pub struct PublishCount(Arc<WakeSegment>, usize);

impl PublishCount {
    /// The count now (one atomic load).
    pub fn get(&self) -> u32 {
        self.0.seq(self.1)
    }
}

/// Wakes a topic's receivers without sending (see [`Topic::poker`]).
pub struct Poker(Notify);

impl Poker {
    /// Wakes the receivers.
    pub fn poke(&self) -> Result<()> {
        match &self.0 {
            Notify::Event(n) => {
                n.notify().map_err(|e| anyhow!("notify: {e:?}"))?;
            }
            Notify::Futex(seg, i) => {
                seg.notify(*i);
                seg.notify(*i + DECIMATED);
            }
        }
        Ok(())
    }
}

// The iceoryx2 port is boxed (allocated once, at set-up): it is ~1.4 kB, the futex variant
// 16 bytes.
enum Notify {
    Event(Box<Notifier<ipc::Service>>),
    Futex(Arc<WakeSegment>, usize),
}

/// A loaned, not yet written sample of a topic.
type Loaned<T> = SampleMutUninit<ipc::Service, std::mem::MaybeUninit<T>, ()>;

/// Publishes a message and wakes the receivers.
pub struct Sender<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> {
    publisher: Publisher<ipc::Service, T, ()>,
    notify: Notify,
    /// The sample the next send writes, loaned after the last wake-up: a loan first
    /// reclaims the chunks the subscribers gave back, a third of a send's cost, and after
    /// the wake-up it runs once the receivers have run (docs/architecture.md, "Where the
    /// microseconds go").
    spare: std::cell::Cell<Option<Loaned<T>>>,
}

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> Sender<T> {
    /// Connects to the subscribers that exist now (otherwise done lazily on the first send).
    pub fn connect(&self) -> Result<()> {
        use iceoryx2::port::update_connections::UpdateConnections;
        self.publisher
            .update_connections()
            .map_err(|e| anyhow!("update connections: {e:?}"))
    }

    /// Copies `msg` into a loaned sample, sends it and wakes the receivers. The loan makes
    /// iceoryx2's one allocation per message (docs/architecture.md, "Real-time rules").
    pub fn send(&self, msg: T) -> Result<()> {
        self.send_waking(msg, false)
    }

    /// [`Sender::send`], waking the topic's decimated receivers too when `decimated`.
    pub fn send_waking(&self, msg: T, decimated: bool) -> Result<()> {
        self.publish(msg)?;
        self.wake(decimated)
    }

    /// Sends `msg` without waking anyone: the first half of [`Sender::send_waking`]. A
    /// producer killed between the two halves leaves a message its readers were not woken
    /// for (a standby twin that takes over wakes them, see [`Sender::wake`]).
    pub fn publish(&self, msg: T) -> Result<()> {
        let s = match self.spare.take() {
            Some(s) => s,
            None => self
                .publisher
                .loan_uninit()
                .map_err(|e| anyhow!("loan: {e:?}"))?,
        };
        s.write_payload(msg)
            .send()
            .map_err(|e| anyhow!("send: {e:?}"))?;
        Ok(())
    }

    /// Wakes the topic's receivers (and its decimated receivers when `decimated`) without
    /// sending: the second half of [`Sender::send_waking`]. It then loans the next message's
    /// sample (iceoryx2's one allocation per message); a system call only for a word that
    /// has sleepers.
    pub fn wake(&self, decimated: bool) -> Result<()> {
        match &self.notify {
            Notify::Event(n) => {
                n.notify().map_err(|e| anyhow!("notify: {e:?}"))?;
            }
            Notify::Futex(seg, i) => {
                let t = crate::rt::now_ns();
                seg.notify_stamped(*i, t);
                if decimated {
                    seg.notify_stamped(*i + DECIMATED, t);
                }
            }
        }
        self.loan_spare();
        Ok(())
    }

    /// Loans the sample the next send writes, if none is held. A failed loan is left to
    /// that send, which loans again and reports the error.
    fn loan_spare(&self) {
        let s = self
            .spare
            .take()
            .or_else(|| self.publisher.loan_uninit().ok());
        self.spare.set(s);
    }
}

// Boxed iceoryx2 port, as in `Notify`.
enum Waiter {
    Polled,
    Event(Box<Listener<ipc::Service>>),
    Futex(Arc<WakeSegment>, usize, std::cell::Cell<u32>),
}

/// Receives messages and waits for their wake-ups.
pub struct Receiver<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> {
    subscriber: Subscriber<ipc::Service, T, ()>,
    waiter: Waiter,
}

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> Receiver<T> {
    /// Connects to the publishers that exist now (otherwise done lazily on the first
    /// receive): a restarted service calls it before its real-time set-up, so that mapping
    /// the running peers' segments is not done at real-time priority.
    pub fn connect(&self) -> Result<()> {
        use iceoryx2::port::update_connections::UpdateConnections;
        self.subscriber
            .update_connections()
            .map_err(|e| anyhow!("update connections: {e:?}"))
    }

    /// True when no message is buffered.
    pub fn is_empty(&self) -> Result<bool> {
        self.subscriber
            .has_samples()
            .map(|h| !h)
            .map_err(|e| anyhow!("has_samples: {e:?}"))
    }

    /// Next buffered message, oldest first.
    pub fn try_recv(&self) -> Result<Option<T>> {
        match self.subscriber.receive() {
            Ok(Some(s)) => Ok(Some(*s)),
            Ok(None) => Ok(None),
            Err(e) => Err(anyhow!("receive: {e:?}")),
        }
    }

    /// When the sender of the newest stamped wake-up on this topic started its notify
    /// (CLOCK_MONOTONIC ns; 0 without futex wake-ups or before the first one).
    #[inline]
    pub fn notified_ns(&self) -> u64 {
        match &self.waiter {
            Waiter::Futex(seg, i, _) => seg.stamp(*i),
            _ => 0,
        }
    }

    /// Blocks until a wake-up arrives or `timeout` passes. Callers loop: wait, then drain
    /// with [`Receiver::try_recv`]. A signal interrupting the wait is not an error (the caller
    /// checks its stop flag). A polled receiver sleeps at most [`POLL_SLEEP`].
    pub fn wait(&self, timeout: Duration) -> Result<()> {
        match &self.waiter {
            Waiter::Polled => {
                std::thread::sleep(timeout.min(POLL_SLEEP));
                Ok(())
            }
            Waiter::Event(listener) => match listener.timed_wait(|_| {}, timeout) {
                Ok(_) => Ok(()),
                Err(iceoryx2::port::listener::ListenerWaitError::InterruptSignal) => Ok(()),
                Err(e) => Err(anyhow!("wait: {e:?}")),
            },
            Waiter::Futex(seg, i, seen) => {
                // A message published before the bump of the word is visible once the bump
                // is seen, so nothing is lost between draining and sleeping.
                let now = seg.seq(*i);
                let now = if now == seen.get() {
                    seg.wait(*i, now, timeout)
                } else {
                    now
                };
                seen.set(now);
                Ok(())
            }
        }
    }
}

/// The drive's topics, opened once per process.
pub struct DriveTopics {
    /// Measurements.
    pub meas: Topic<crate::messages::Measurement>,
    /// Estimates.
    pub est: Topic<crate::messages::Estimate>,
    /// Current references.
    pub iref: Topic<crate::messages::CurrentRef>,
    /// Voltage commands.
    pub cmd: Topic<crate::messages::VoltageCommand>,
    /// Recorder progress: highest k below which every sample has been stored.
    pub rec: Topic<u64>,
    /// Speed references of an outer loop.
    pub wref: Topic<crate::messages::SpeedRef>,
    /// The plant's true state (recorder only).
    pub truth: Topic<crate::messages::PlantTruth>,
    _seg: Option<Arc<WakeSegment>>,
}

impl DriveTopics {
    /// Opens (or creates) all topics with iceoryx2 events for wake-ups.
    pub fn open(node: &Node<ipc::Service>) -> Result<Self> {
        Self::open_with(node, WakeKind::Iceoryx2, "")
    }

    /// Opens (or creates) all topics of bus `bus_id` with the given wake-up mechanism.
    pub fn open_with(node: &Node<ipc::Service>, wake: WakeKind, bus_id: &str) -> Result<Self> {
        Self::open_for(node, wake, bus_id, 1)
    }

    /// [`DriveTopics::open_with`] with `publishers` publishers per topic (2 in a drive with
    /// standby twins; see [`Topic::open_shared`]).
    pub fn open_for(
        node: &Node<ipc::Service>,
        wake: WakeKind,
        bus_id: &str,
        publishers: usize,
    ) -> Result<Self> {
        let seg = match wake {
            WakeKind::Iceoryx2 => None,
            WakeKind::Futex => Some(Arc::new(WakeSegment::open(bus_id)?)),
        };
        let w = |i: usize| seg.as_ref().map(|s| (s.clone(), i));
        Ok(Self {
            meas: Topic::open_shared(node, TOPIC_MEAS, w(0), publishers)
                .context("measurement topic")?,
            est: Topic::open_shared(node, TOPIC_EST, w(1), publishers).context("estimate topic")?,
            iref: Topic::open_shared(node, TOPIC_IREF, w(2), publishers)
                .context("current-reference topic")?,
            cmd: Topic::open_shared(node, TOPIC_CMD, w(3), publishers).context("command topic")?,
            rec: Topic::open_shared(node, TOPIC_REC, w(4), publishers).context("recorder topic")?,
            wref: Topic::open_shared(node, TOPIC_WREF, w(5), publishers)
                .context("speed-reference topic")?,
            truth: Topic::open_shared(node, TOPIC_TRUTH, w(6), publishers)
                .context("plant-truth topic")?,
            _seg: seg.clone(),
        })
    }
}

/// True when /dev/shm file `name` belongs to bus `id`: the bus prefix followed by the futex
/// segment (`wake`), the liveness segment (`life`) or an iceoryx2 name (40 hex digits, then `_` or `.`). Bus ids may contain
/// `_`, so the prefix alone would also match bus `<id>_x`.
pub fn owned_by(name: &str, id: &str) -> bool {
    let Some(rest) = name.strip_prefix(&shm_prefix(id)) else {
        return false;
    };
    // The futex segment and the liveness segment.
    if rest == "wake" || rest == "life" {
        return true;
    }
    let b = rest.as_bytes();
    b.len() > 40 && b[..40].iter().all(|c| c.is_ascii_hexdigit()) && matches!(b[40], b'_' | b'.')
}

/// Removes every file of bus `id` (shared memory and the root folder). Returns how many
/// shared-memory files were removed. Call only when no process of the bus runs.
pub fn cleanup(id: &str) -> Result<usize> {
    check_bus_id(id)?;
    // Refuse a bus folder that is a link before anything is removed.
    let root = root_path(id);
    let root_exists = check_folder(std::path::Path::new(&root))?;
    let mut n = 0;
    if let Ok(rd) = std::fs::read_dir("/dev/shm") {
        for e in rd.flatten() {
            if owned_by(&e.file_name().to_string_lossy(), id) {
                std::fs::remove_file(e.path())
                    .with_context(|| format!("remove {}", e.path().display()))?;
                n += 1;
            }
        }
    }
    if root_exists {
        std::fs::remove_dir_all(&root).with_context(|| format!("remove {root}"))?;
    }
    Ok(n)
}

/// Files of bus `id` that still exist (for tests and the final check of a run).
pub fn leftovers(id: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir("/dev/shm")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| owned_by(n, id))
        .map(|n| format!("/dev/shm/{n}"))
        .collect();
    if std::fs::symlink_metadata(root_path(id).trim_end_matches('/')).is_ok() {
        v.push(root_path(id));
    }
    v
}

/// Removes bus `id`'s files when dropped, also when a test fails (tests only).
#[cfg(test)]
pub(crate) struct CleanupOnDrop(pub String);

#[cfg(test)]
impl Drop for CleanupOnDrop {
    fn drop(&mut self) {
        let _ = cleanup(&self.0);
    }
}

/// Supervisor helper: lists the nodes of bus `id` through iceoryx2's node liveness, removes
/// the stale resources of every dead one, and returns the dead nodes' names.
pub fn reap_dead_nodes(id: &str) -> Result<Vec<String>> {
    use iceoryx2::node::NodeView;
    let cfg = config(id)?;
    let mut dead = Vec::new();
    Node::<ipc::Service>::list(&cfg, |state| {
        if let NodeState::Dead(view) = state {
            let name = view
                .details()
                .as_ref()
                .map(|d| d.name().to_string())
                .unwrap_or_else(|| "?".into());
            let _ = view.try_remove_stale_resources();
            dead.push(name);
        }
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow!("cannot list the nodes of bus {id}: {e:?}"))?;
    Ok(dead)
}

/// Holds the bus's publisher data segments open from the launcher, so that the kernel frees
/// a dead process's segments there and not inside a real-time loop.
///
/// When a process dies, every host that read its topics drops its mapping of the dead
/// publisher's data segment at its next receive (iceoryx2 updates connections there), and
/// whichever process drops the last reference frees the segment's pages: about 0.4 ms for
/// the 3.3 MB estimate segment on the measured VM, inside the loop of a stage that wakes only
/// when the restarted peer publishes again (docs/architecture.md, "Liveness words and
/// standby twins"). With the launcher holding a descriptor of each segment, the hosts' drops
/// only unmap, and the pages are freed when [`SegmentKeeper::release_removed`] closes the
/// descriptor, on the launcher's CPUs. Only open descriptors: nothing is mapped or created.
pub struct SegmentKeeper {
    id: String,
    held: Vec<HeldSegment>,
    checked: Option<std::time::Instant>,
}

struct HeldSegment {
    file: std::fs::File,
    dev_ino: (u64, u64),
    /// When the linger began: the file seen removed with no process starting.
    removed: Option<std::time::Instant>,
    /// When the file was first seen removed from /dev/shm.
    first_removed: Option<std::time::Instant>,
}

impl SegmentKeeper {
    /// How long a removed segment is held after it was seen removed and no process was
    /// starting: the readers that are woken by the restarted peer drop theirs by then.
    pub const LINGER: Duration = Duration::from_secs(1);
    /// The longest a removed segment is held, processes starting or not: restarts that
    /// follow each other closely (a crash loop, many kills) do not pile segments up.
    pub const HOLD_MAX: Duration = Duration::from_secs(3);
    /// The shortest time between two checks of the held segments (an `fstat` each).
    const CHECK_EVERY: Duration = Duration::from_millis(100);

    /// Holds nothing yet; see [`Self::hold_new`].
    pub fn new(id: &str) -> Self {
        Self {
            id: id.into(),
            held: Vec::new(),
            checked: None,
        }
    }

    /// Opens the bus's data segments (`*.data`) that are not held yet. Call it when a
    /// process has made its ports (READY) and before dead nodes are reaped. A segment
    /// removed before it could be opened is skipped (its last reader frees it).
    pub fn hold_new(&mut self) {
        use std::os::unix::fs::MetadataExt;
        let Ok(rd) = std::fs::read_dir("/dev/shm") else {
            return;
        };
        for e in rd.flatten() {
            let name = e.file_name();
            let name = name.to_string_lossy();
            if !name.ends_with(".data") || !owned_by(&name, &self.id) {
                continue;
            }
            let Ok(file) = std::fs::File::open(e.path()) else {
                continue;
            };
            let Ok(m) = file.metadata() else {
                continue;
            };
            let dev_ino = (m.dev(), m.ino());
            if !self.held.iter().any(|h| h.dev_ino == dev_ino) {
                self.held.push(HeldSegment {
                    file,
                    dev_ino,
                    removed: None,
                    first_removed: None,
                });
            }
        }
    }

    /// Closes the held segments that were removed from /dev/shm at least [`Self::LINGER`]
    /// ago, counted only while `starting` is false (a process is starting or restarting:
    /// its peers drop the dead one's segments when it publishes), and any removed
    /// [`Self::HOLD_MAX`] ago. At most one check every 100 ms. Returns how many were closed.
    pub fn release_removed(&mut self, now: std::time::Instant, starting: bool) -> usize {
        use std::os::unix::fs::MetadataExt;
        if self
            .checked
            .is_some_and(|t| now.duration_since(t) < Self::CHECK_EVERY)
        {
            return 0;
        }
        self.checked = Some(now);
        let before = self.held.len();
        self.held.retain_mut(|h| {
            let gone = h.file.metadata().map_or(true, |m| m.nlink() == 0);
            if !gone {
                return true;
            }
            let first = *h.first_removed.get_or_insert(now);
            if now.duration_since(first) >= Self::HOLD_MAX {
                return false;
            }
            if starting {
                h.removed = Some(now);
                return true;
            }
            let since = *h.removed.get_or_insert(now);
            now.duration_since(since) < Self::LINGER
        });
        before - self.held.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The launcher's keeper holds the bus's data segments (and only those), keeps a removed
    /// one readable while a process is starting and for a second after, then closes it.
    #[test]
    fn the_segment_keeper_holds_data_segments_until_they_have_been_removed_a_while() {
        use std::io::{Read, Seek};
        use std::time::Instant;
        let id = format!("kp{}", std::process::id());
        let _cleanup = CleanupOnDrop(id.clone());
        let hex = "0123456789abcdef0123456789abcdef01234567";
        let data = format!("/dev/shm/{}{hex}_42.data", shm_prefix(&id));
        let other = format!("/dev/shm/{}{hex}_42.dynamic", shm_prefix(&id));
        let foreign_id = format!("{id}_x");
        let _cleanup_foreign = CleanupOnDrop(foreign_id.clone());
        let foreign = format!("/dev/shm/{}{hex}_7.data", shm_prefix(&foreign_id));
        for f in [&data, &other, &foreign] {
            std::fs::write(f, b"segment").unwrap();
        }
        let mut keeper = SegmentKeeper::new(&id);
        keeper.hold_new();
        keeper.hold_new();
        assert_eq!(keeper.held.len(), 1, "only this bus's data segment, once");
        let t0 = Instant::now();
        assert_eq!(keeper.release_removed(t0, false), 0, "not removed yet");
        std::fs::remove_file(&data).unwrap();
        // Removed while a process is starting: held however long that takes.
        let ms = |n| Duration::from_millis(n);
        assert_eq!(keeper.release_removed(t0 + ms(200), true), 0);
        assert_eq!(keeper.release_removed(t0 + ms(1500), true), 0);
        // The linger counts from the last check that saw a process starting.
        assert_eq!(keeper.release_removed(t0 + ms(1700), false), 0);
        assert_eq!(keeper.release_removed(t0 + ms(2450), false), 0);
        // Checks closer than 100 ms apart do nothing.
        assert_eq!(keeper.release_removed(t0 + ms(2510), false), 0);
        let mut text = String::new();
        let held = &mut keeper.held[0].file;
        held.rewind().unwrap();
        held.read_to_string(&mut text).unwrap();
        assert_eq!(text, "segment", "the removed segment is still held");
        assert_eq!(keeper.release_removed(t0 + ms(2800), false), 1);
        assert_eq!(keeper.held.len(), 0);
        // Processes starting one after another: held at most HOLD_MAX after its removal.
        std::fs::write(&data, b"segment").unwrap();
        keeper.hold_new();
        std::fs::remove_file(&data).unwrap();
        let t1 = t0 + ms(3000);
        assert_eq!(keeper.release_removed(t1, true), 0);
        assert_eq!(keeper.release_removed(t1 + ms(2900), true), 0);
        assert_eq!(keeper.release_removed(t1 + ms(3000), true), 1);
        // A segment removed before it could be held is skipped.
        keeper.hold_new();
        assert_eq!(keeper.held.len(), 0);
    }

    #[test]
    fn the_shared_folder_must_be_roots_or_this_users() {
        let p = std::path::Path::new("/tmp/iceoryx2");
        assert!(check_shared_owner(p, 0, 1000).is_ok());
        assert!(check_shared_owner(p, 1000, 1000).is_ok());
        assert!(check_shared_owner(p, 0, 0).is_ok());
        let e = check_shared_owner(p, 65534, 0).unwrap_err().to_string();
        assert_eq!(
            e,
            "/tmp/iceoryx2 belongs to uid 65534, neither root nor this user (uid 0): its owner could replace this user's bus folders; as root, remove it (drivelab makes it again) or `chown root /tmp/iceoryx2`"
        );
        assert!(check_shared_owner(p, 1001, 1000).is_err());
    }

    /// A sender holds the sample its next send writes, loaned after each wake-up: across
    /// many more sends than it may loan at once, and with publishes that no wake-up follows
    /// (a standby twin's takeover), every message arrives once and in order.
    #[test]
    fn a_sender_holding_its_next_sample_delivers_every_message_once_in_order() {
        let bus = format!("bsp{}", std::process::id());
        let _cleanup = CleanupOnDrop(bus.clone());
        let node = node(&bus, "spare").unwrap();
        let topics = DriveTopics::open_with(&node, WakeKind::Futex, &bus).unwrap();
        let rx = topics.est.receiver(4).unwrap();
        let tx = topics.est.sender().unwrap();
        let est = |k: u64| crate::messages::Estimate {
            hdr: crate::messages::Header {
                k,
                ..Default::default()
            },
            omega_m: k as f64,
            ..Default::default()
        };
        let got = |rx: &Receiver<crate::messages::Estimate>| {
            rx.try_recv().unwrap().map(|m| (m.hdr.k, m.omega_m))
        };
        for k in 0..1000 {
            tx.send(est(k)).unwrap();
            assert_eq!(got(&rx), Some((k, k as f64)));
        }
        for k in 1000..1003 {
            tx.publish(est(k)).unwrap();
        }
        tx.wake(false).unwrap();
        for k in 1000..1003 {
            assert_eq!(got(&rx), Some((k, k as f64)));
        }
        assert_eq!(got(&rx), None);
        drop((tx, rx, topics, node));
    }

    #[test]
    fn bus_files_are_told_apart_by_id() {
        let hash = "b9fc73e5c1f646968758453273c6c65cb372831b";
        assert!(owned_by("iox2_dlab_wake", "ab"));
        assert!(owned_by("iox2_dlab_life", "ab"));
        assert!(!owned_by("iox2_dlab_c_life", "ab"));
        assert!(owned_by(
            &format!("iox2_dlab_{hash}_7922874017454358376"),
            "ab"
        ));
        assert!(owned_by(&format!("iox2_dlab_{hash}.data"), "ab"));
        // Bus "ab_c" shares the prefix "iox2_dlab_" but not the names.
        assert!(!owned_by("iox2_dlab_c_wake", "ab"));
        assert!(!owned_by(&format!("iox2_dlab_c_{hash}_1"), "ab"));
        assert!(owned_by(&format!("iox2_dlab_c_{hash}_1"), "ab_c"));
        assert!(!owned_by("something_else", "ab"));
    }
}
