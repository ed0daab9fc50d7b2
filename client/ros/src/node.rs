//! The node: DDS subscriptions and publications, frame pairing, the rate limit, and the loop that
//! sends frames to the server and publishes its answers.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};
use futures::StreamExt;
use nalgebra::Isometry3;
use ros2_client::qos::{Durability, History, Reliability, WhenFull};
use ros2_client::{
    Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher,
    QosProfile, ServiceMapping, ServiceTypeName, Subscription,
};
use rustdds::Topic;
use serde::de::DeserializeOwned;
use tokio::sync::watch;

use crate::frames::{self, Received};
use crate::grpc::{Link, Target};
use crate::msgs::{self, types, Time};
use crate::params::RosArgs;
use crate::{answer, proto, tf};

/// One colour image and the depth image taken with it.
#[derive(Clone)]
struct Frame {
    rgb: Received,
    depth: Received,
}

/// Counters and the last answer, for /diagnostics.
#[derive(Default)]
struct Stats {
    pairs: u64,
    sent: u64,
    localized: u64,
    not_localized: u64,
    /// Frames not sent: their transforms or camera_info were missing, or a message was unusable.
    skipped: u64,
    /// Frames the server could not answer (unreachable, stream broken).
    failed: u64,
    /// When a frame was last skipped.
    last_skip: Option<Instant>,
    /// The server refused (a missing map, a wrong token) rather than being away.
    refused: bool,
    last_status: String,
    last_reason: String,
    /// The server's word on the stream's track after the last answer (`TRACK_STATE_...`).
    last_track: String,
    last_latency_ms: f64,
    map_id: String,
    map_version: String,
    connected: bool,
    last_answer: Option<Instant>,
}

/// What the tasks share.
struct Shared {
    tf: tf::Buffer,
    info: Option<msgs::CameraInfo>,
    rgb: VecDeque<Received>,
    depth: VecDeque<Received>,
    /// The newest stamp of any camera message (re-broadcasts of `map -> odom` follow it).
    newest_stamp: Time,
    map_from_odom: Option<Isometry3<f64>>,
    /// A pose from `initialpose` not yet used.
    initial: Option<InitialPose>,
    stats: Stats,
}

type State = Arc<Mutex<Shared>>;

fn lock(s: &State) -> std::sync::MutexGuard<'_, Shared> {
    s.lock().unwrap_or_else(|e| e.into_inner())
}

/// Sensor data as camera drivers publish it: best effort (a best-effort reader also matches a
/// reliable writer), the last few kept.
const SENSOR: QosProfile =
    QosProfile::subscription_default().history(History::KeepLast { depth: 5 });
const RELIABLE: QosProfile = QosProfile::publisher_default()
    .reliability(Reliability::Reliable {
        when_full: WhenFull::Wait(Duration::from_millis(50)),
    })
    .history(History::KeepLast { depth: 100 });
/// /tf_static as tf2 listens to it: reliable and transient local, so a late joiner gets it.
const LATCHED: QosProfile = RELIABLE.durability(Durability::TransientLocal);

/// The topic `name` (already resolved) of type `kind`.
fn topic(node: &mut Node, name: &str, kind: MessageTypeName, qos: &QosProfile) -> Result<Topic> {
    let parsed = Name::parse(name).map_err(|e| anyhow::anyhow!("topic {name}: {e:?}"))?;
    node.create_topic(&parsed, kind, qos)
        .map_err(|e| anyhow::anyhow!("topic {name}: {e:?}"))
}

fn subscribe<M: DeserializeOwned + 'static>(
    node: &mut Node,
    name: &str,
    kind: MessageTypeName,
    qos: QosProfile,
) -> Result<Subscription<M>> {
    let t = topic(node, name, kind, &qos)?;
    node.create_subscription(&t, Some(qos))
        .map_err(|e| anyhow::anyhow!("subscription {name}: {e:?}"))
}

fn advertise<M: serde::Serialize>(
    node: &mut Node,
    name: &str,
    kind: MessageTypeName,
    qos: QosProfile,
) -> Result<Publisher<M>> {
    let t = topic(node, name, kind, &qos)?;
    node.create_publisher(&t, Some(qos))
        .map_err(|e| anyhow::anyhow!("publisher {name}: {e:?}"))
}

/// A subscription of colour or depth: raw, or compressed when the topic's last part says so.
enum ImageSub {
    Raw(Subscription<msgs::Image>),
    Compressed(Subscription<msgs::CompressedImage>),
}

fn image_subscription(node: &mut Node, name: &str) -> Result<ImageSub> {
    Ok(
        if name.ends_with("/compressed") || name.ends_with("/compressedDepth") {
            ImageSub::Compressed(subscribe(node, name, types::compressed_image(), SENSOR)?)
        } else {
            ImageSub::Raw(subscribe(node, name, types::image(), SENSOR)?)
        },
    )
}

/// Take messages of `sub` for ever, each given to `each`.
async fn drain<M: DeserializeOwned + 'static>(
    sub: Subscription<M>,
    name: String,
    mut each: impl FnMut(M),
) {
    let stream = sub.async_stream();
    futures::pin_mut!(stream);
    while let Some(r) = stream.next().await {
        match r {
            Ok((m, _)) => each(m),
            Err(e) => tracing::warn!("{name}: a message could not be read: {e:?}"),
        }
    }
}

/// Keep a received colour or depth message and pair the newest colour with a depth image of its
/// stamp (within `slop_ns`): the pair replaces the waiting one (an unsent older pair is dropped).
fn arrived(
    state: &State,
    frame_tx: &watch::Sender<Option<Frame>>,
    m: Received,
    rgb: bool,
    slop_ns: i64,
) {
    let mut s = lock(state);
    let stamp = m.header().stamp;
    s.newest_stamp = s.newest_stamp.max(stamp);
    let queue = if rgb { &mut s.rgb } else { &mut s.depth };
    queue.push_back(m);
    if queue.len() > 8 {
        queue.pop_front();
    }
    let pair = s.rgb.iter().rev().find_map(|c| {
        let t = c.header().stamp.nanos();
        s.depth
            .iter()
            .rev()
            .find(|d| (d.header().stamp.nanos() - t).abs() <= slop_ns)
            .map(|d| (c.clone(), d.clone(), t))
    });
    if let Some((rgb, depth, t)) = pair {
        s.rgb.retain(|c| c.header().stamp.nanos() > t);
        s.depth.retain(|d| d.header().stamp.nanos() > t + slop_ns);
        s.stats.pairs += 1;
        frame_tx.send_replace(Some(Frame { rgb, depth }));
    }
}

/// The rate limit, on the frames' own stamps: slots `1 / rate_hz` apart; the first frame whose stamp
/// reaches a slot (a quarter period early at most, for a camera's jitter) takes it and is sent as
/// soon as it arrives, so what is sent is never older than the camera's period plus the previous
/// answer's time; frames between slots are dropped. A slot a camera cannot fill is not made up later
/// (no burst after a pause), so at most `rate_hz` frames a second are sent over any stretch of time.
/// Stamps that go back (a bag played again) start the slots afresh.
struct Slots {
    period_ns: i64,
    due_ns: Option<i64>,
    last_ns: i64,
}

impl Slots {
    fn new(rate_hz: f64) -> Self {
        Self {
            period_ns: (1e9 / rate_hz) as i64,
            due_ns: None,
            last_ns: i64::MIN,
        }
    }

    /// Whether the frame stamped `stamp_ns` takes a slot.
    fn take(&mut self, stamp_ns: i64) -> bool {
        if stamp_ns < self.last_ns {
            self.due_ns = None;
        }
        if let Some(due) = self.due_ns {
            if stamp_ns < due - self.period_ns / 4 {
                return false;
            }
        }
        self.due_ns = Some(match self.due_ns {
            Some(due) if stamp_ns < due + self.period_ns => due + self.period_ns,
            _ => stamp_ns + self.period_ns,
        });
        self.last_ns = stamp_ns;
        true
    }
}

/// A pose given on `initialpose` (RViz's "2D Pose Estimate", as AMCL takes it): the next frame is
/// searched for near it, over the whole map (the track dropped), with the pose as a prior.
#[derive(Clone, Copy, Debug)]
struct InitialPose {
    map_from_base: Isometry3<f64>,
    /// Three standard deviations of the position (the largest of x and y), at least 0.5 m.
    radius_m: f64,
}

impl InitialPose {
    fn of(m: &msgs::PoseWithCovarianceStamped) -> Option<Self> {
        let pose = tf::isometry(&msgs::Transform {
            translation: m.pose.pose.position,
            rotation: m.pose.pose.orientation,
        });
        let c = &m.pose.covariance;
        let sigma = c[0].max(c[7]).max(0.0).sqrt();
        (pose.translation.vector.iter().all(|v| v.is_finite()) && sigma.is_finite()).then_some(
            Self {
                map_from_base: pose,
                radius_m: (3.0 * sigma).max(0.5),
            },
        )
    }

    /// The prior of the camera mounted at `base_from_camera`.
    fn prior(&self, base_from_camera: &Isometry3<f64>) -> proto::Prior {
        proto::Prior {
            pose: Some(pose_message(&(self.map_from_base * base_from_camera))),
            covariance: Vec::new(),
            radius_m: self.radius_m,
        }
    }
}

/// A pose as the wire carries it.
fn pose_message(p: &Isometry3<f64>) -> proto::Pose {
    let q = p.rotation.quaternion();
    proto::Pose {
        translation: Some(proto::Vector3 {
            x: p.translation.x,
            y: p.translation.y,
            z: p.translation.z,
        }),
        rotation: Some(proto::Quaternion {
            w: q.w,
            x: q.i,
            y: q.j,
            z: q.k,
        }),
    }
}

/// The request of one frame, with the transforms its answer needs: (request, base_from_camera,
/// odom_from_base). Waits up to 0.3 s for transforms that have not arrived yet (odometry a little
/// behind the camera), as tf2's message filter does.
async fn request_of(
    state: &State,
    ros: &RosArgs,
    f: &Frame,
    map_id: &str,
    relocalize: bool,
    initial: Option<&InitialPose>,
) -> Result<(proto::LocalizeRequest, Isometry3<f64>, Isometry3<f64>), String> {
    let p = &ros.params;
    let header = f.rgb.header().clone();
    let stamp = header.stamp.nanos();
    let camera = header.frame_id.trim_start_matches('/').to_string();
    if camera.is_empty() {
        return Err("the colour image has no header.frame_id (its optical frame)".into());
    }
    let rgb = frames::colour(&f.rgb)?;
    let depth = frames::depth(&f.depth)?;
    let deadline = Instant::now() + Duration::from_millis(300);
    loop {
        let attempt = {
            let s = lock(state);
            let info = s
                .info
                .clone()
                .ok_or_else(|| format!("no camera_info on {} yet", ros.resolve(&p.info_topic)))?;
            let intrinsics = frames::intrinsics(&info, (rgb.width, rgb.height))?;
            s.tf.lookup(&p.base_frame, &camera, stamp)
                .and_then(|b| Ok((b, s.tf.lookup(&p.odom_frame, &p.base_frame, stamp)?)))
                .map(|(base_from_camera, odom_from_base)| {
                    (intrinsics, base_from_camera, odom_from_base)
                })
        };
        match attempt {
            Ok((intrinsics, base_from_camera, odom_from_base)) => {
                let request = proto::LocalizeRequest {
                    map_id: map_id.to_string(),
                    rgb: Some(rgb),
                    depth: Some(depth),
                    intrinsics: Some(intrinsics),
                    request_id: format!("{}.{:09}", header.stamp.sec, header.stamp.nanosec),
                    prior: initial.map(|i| i.prior(&base_from_camera)),
                    relocalize: relocalize || initial.is_some(),
                    frame_convention: proto::FrameConvention::Ros as i32,
                    // The camera's time: the server judges motion by it, not by arrival.
                    stamp_s: Some(stamp as f64 * 1e-9),
                    // The robot's odometry of the camera: the stream carries its pose by it
                    // where the map gives no fix.
                    odometry: Some(pose_message(&(odom_from_base * base_from_camera))),
                    continuation: None,
                };
                return Ok((request, base_from_camera, odom_from_base));
            }
            Err(e) if Instant::now() >= deadline => return Err(format!("transform: {e}")),
            Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
}

fn tf_message(ros: &RosArgs, map_from_odom: &Isometry3<f64>, stamp: Time) -> msgs::TfMessage {
    msgs::TfMessage {
        transforms: vec![msgs::TransformStamped {
            header: msgs::Header {
                stamp,
                frame_id: ros.params.map_frame.clone(),
            },
            child_frame_id: ros.params.odom_frame.clone(),
            transform: tf::transform(map_from_odom),
        }],
    }
}

fn plus_seconds(t: Time, s: f64) -> Time {
    Time::from_nanos(t.nanos() + (s * 1e9) as i64)
}

/// Run the node until SIGINT or SIGTERM.
pub async fn run(ros: RosArgs, target: Target, map_id: String) -> Result<()> {
    let mut link = Link::new(target.clone())?;
    let domain: u16 = match std::env::var("ROS_DOMAIN_ID") {
        Ok(v) if !v.trim().is_empty() => v
            .trim()
            .parse()
            .ok()
            .filter(|d| *d <= 232)
            .with_context(|| format!("ROS_DOMAIN_ID={v:?}: a domain is 0 to 232"))?,
        _ => 0,
    };
    // The service's wire format differs between RMWs (rmw_cyclonedds puts a request header in the
    // payload; Fast DDS uses RTPS sample identities). RMW_IMPLEMENTATION names the robot's RMW as
    // its other nodes read it; unset, both are served (each ignores the other's requests, which it
    // cannot decode, or answers them in a form the other's clients drop).
    let rmw = std::env::var("RMW_IMPLEMENTATION").unwrap_or_default();
    let mappings: &[(ServiceMapping, &str)] = if rmw.contains("cyclonedds") {
        &[(ServiceMapping::Cyclone, "cyclonedds")]
    } else if rmw.contains("fastrtps") || rmw.contains("fastdds") {
        &[(ServiceMapping::Enhanced, "fastdds")]
    } else {
        &[
            (ServiceMapping::Enhanced, "fastdds"),
            (ServiceMapping::Cyclone, "cyclonedds"),
        ]
    };
    let context = Context::with_options(ContextOptions::new().domain_id(domain))
        .map_err(|e| anyhow::anyhow!("DDS participant on domain {domain}: {e:?}"))?;
    let mut node = context
        .new_node(
            NodeName::new(&ros.namespace, &ros.node_name).map_err(|e| {
                anyhow::anyhow!(
                    "node {:?} in namespace {:?}: {e:?} (names are letters, digits and underscores, not starting with a digit)",
                    ros.node_name,
                    ros.namespace
                )
            })?,
            NodeOptions::new().enable_rosout(false),
        )
        .map_err(|e| anyhow::anyhow!("ROS node: {e:?}"))?;
    let p = ros.params.clone();
    let rgb_sub = image_subscription(&mut node, &ros.resolve(&p.rgb_topic))?;
    let depth_sub = image_subscription(&mut node, &ros.resolve(&p.depth_topic))?;
    let info_sub: Subscription<msgs::CameraInfo> = subscribe(
        &mut node,
        &ros.resolve(&p.info_topic),
        types::camera_info(),
        SENSOR,
    )?;
    let tf_sub: Subscription<msgs::TfMessage> = subscribe(
        &mut node,
        &ros.resolve("/tf"),
        types::tf_message(),
        RELIABLE,
    )?;
    let tf_static_sub: Subscription<msgs::TfMessage> = subscribe(
        &mut node,
        &ros.resolve("/tf_static"),
        types::tf_message(),
        LATCHED,
    )?;
    let initial_sub: Subscription<msgs::PoseWithCovarianceStamped> = subscribe(
        &mut node,
        &ros.resolve("initialpose"),
        types::pose_with_covariance_stamped(),
        RELIABLE.history(History::KeepLast { depth: 1 }),
    )?;
    let pose_pub: Publisher<msgs::PoseWithCovarianceStamped> = advertise(
        &mut node,
        &ros.resolve(&p.pose_topic),
        types::pose_with_covariance_stamped(),
        RELIABLE.history(History::KeepLast { depth: 10 }),
    )?;
    let tf_pub: Publisher<msgs::TfMessage> = advertise(
        &mut node,
        &ros.resolve("/tf"),
        types::tf_message(),
        RELIABLE,
    )?;
    let diag_pub: Publisher<msgs::DiagnosticArray> = advertise(
        &mut node,
        &ros.resolve("/diagnostics"),
        types::diagnostic_array(),
        RELIABLE.history(History::KeepLast { depth: 10 }),
    )?;
    let service_qos = QosProfile::publisher_default().history(History::KeepLast { depth: 10 });
    let service_name = ros.resolve(&p.relocalize_service);
    let mut servers = Vec::new();
    for (mapping, _) in mappings {
        servers.push(
            node.create_server::<msgs::TriggerRequest, msgs::TriggerResponse>(
                *mapping,
                &Name::parse(&service_name)
                    .map_err(|e| anyhow::anyhow!("service {service_name}: {e:?}"))?,
                &ServiceTypeName::new("std_srvs", "Trigger"),
                service_qos.clone(),
                service_qos.clone(),
            )
            .map_err(|e| anyhow::anyhow!("service {service_name}: {e:?}"))?,
        );
    }
    let spinner = node
        .spinner()
        .map_err(|e| anyhow::anyhow!("ROS spinner: {e:?}"))?;
    tokio::spawn(async move {
        if let Err(e) = spinner.spin().await {
            tracing::warn!("ROS spinner: {e:?}");
        }
    });
    tracing::info!(
        node = %format!("{}/{}", ros.namespace.trim_end_matches('/'), ros.node_name),
        domain,
        rgb = %ros.resolve(&p.rgb_topic),
        depth = %ros.resolve(&p.depth_topic),
        info = %ros.resolve(&p.info_topic),
        pose = %ros.resolve(&p.pose_topic),
        relocalize = %service_name,
        service_mappings = %mappings.iter().map(|(_, n)| *n).collect::<Vec<_>>().join(","),
        frames = %format!("{} <- {} -> {}", p.map_frame, p.odom_frame, p.base_frame),
        rate_hz = p.rate_hz,
        publish_tf = p.publish_tf,
        server = %target.addr,
        "pntr-ros running"
    );

    let state: State = Arc::new(Mutex::new(Shared {
        tf: tf::Buffer::default(),
        info: None,
        rgb: VecDeque::new(),
        depth: VecDeque::new(),
        newest_stamp: Time::default(),
        map_from_odom: None,
        initial: None,
        stats: Stats::default(),
    }));
    let (frame_tx, mut frame_rx) = watch::channel::<Option<Frame>>(None);
    let frame_tx = Arc::new(frame_tx);
    let slop_ns = (p.sync_slop_s * 1e9) as i64;
    for (sub, is_rgb, name) in [
        (rgb_sub, true, ros.resolve(&p.rgb_topic)),
        (depth_sub, false, ros.resolve(&p.depth_topic)),
    ] {
        let (state, tx) = (state.clone(), frame_tx.clone());
        match sub {
            ImageSub::Raw(s) => tokio::spawn(drain(s, name, move |m| {
                arrived(&state, &tx, Received::Raw(m), is_rgb, slop_ns)
            })),
            ImageSub::Compressed(s) => tokio::spawn(drain(s, name, move |m| {
                arrived(&state, &tx, Received::Compressed(m), is_rgb, slop_ns)
            })),
        };
    }
    {
        let s = state.clone();
        tokio::spawn(drain(info_sub, "camera_info".into(), move |m| {
            lock(&s).info = Some(m)
        }));
        let (s, map_frame) = (state.clone(), p.map_frame.clone());
        tokio::spawn(drain(initial_sub, "initialpose".into(), move |m| {
            let frame = m.header.frame_id.trim_start_matches('/');
            match InitialPose::of(&m) {
                Some(i) if frame == map_frame => {
                    tracing::info!(
                        x = i.map_from_base.translation.x,
                        y = i.map_from_base.translation.y,
                        radius_m = i.radius_m,
                        "initial pose given: the next frame is searched for near it"
                    );
                    lock(&s).initial = Some(i);
                }
                _ => tracing::warn!(
                    "initialpose in frame {frame:?} ignored: poses in {map_frame:?} with finite values are taken"
                ),
            }
        }));
        let s = state.clone();
        tokio::spawn(drain(tf_sub, "/tf".into(), move |m| {
            lock(&s).tf.add(&m, false)
        }));
        let s = state.clone();
        tokio::spawn(drain(tf_static_sub, "/tf_static".into(), move |m| {
            lock(&s).tf.add(&m, true)
        }));
    }
    let relocalize = Arc::new(AtomicBool::new(false));
    for server in servers {
        let relocalize = relocalize.clone();
        tokio::spawn(async move {
            loop {
                match server.async_receive_request().await {
                    Ok((id, _)) => {
                        // Served in both formats, one request may reach two servers: said once.
                        if !relocalize.swap(true, Ordering::SeqCst) {
                            tracing::info!(
                                "relocalize requested: the next frame is searched over the whole map"
                            );
                        }
                        let reply = msgs::TriggerResponse {
                            success: true,
                            message: "the track is dropped: the next frame is searched over the whole map".into(),
                        };
                        if let Err(e) = server.async_send_response(id, reply).await {
                            tracing::warn!("relocalize reply: {e:?}");
                        }
                    }
                    // The other RMW's requests, when both are served.
                    Err(e) => tracing::debug!("relocalize request not read: {e:?}"),
                }
            }
        });
    }
    let tf_pub = Arc::new(tf_pub);
    // map -> odom again between answers, so TF lookups never go stale (as AMCL does).
    if p.publish_tf && p.tf_publish_rate_hz > 0.0 {
        let (state, tf_pub, ros) = (state.clone(), tf_pub.clone(), ros.clone());
        tokio::spawn(async move {
            let mut tick =
                tokio::time::interval(Duration::from_secs_f64(1.0 / ros.params.tf_publish_rate_hz));
            loop {
                tick.tick().await;
                let (m, stamp) = {
                    let s = lock(&state);
                    (s.map_from_odom, s.newest_stamp)
                };
                if let Some(m) = m {
                    let stamp = plus_seconds(stamp, ros.params.transform_tolerance_s);
                    let _ = tf_pub.async_publish(tf_message(&ros, &m, stamp)).await;
                }
            }
        });
    }
    // /diagnostics once a second.
    {
        let (state, ros, addr, started) = (
            state.clone(),
            ros.clone(),
            target.addr.clone(),
            Instant::now(),
        );
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tick.tick().await;
                let array = diagnostics(&lock(&state).stats, &ros, &addr, started.elapsed());
                let _ = diag_pub.async_publish(array).await;
            }
        });
    }

    let mut slots = Slots::new(p.rate_hz);
    let shutdown = shutdown_signal();
    futures::pin_mut!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            changed = frame_rx.changed() => if changed.is_err() { break },
        }
        // The newest frame, sent at once when its slot has come (a frame that arrived while the
        // previous one was being answered waits here and is replaced by newer ones).
        let Some(frame) = frame_rx.borrow_and_update().clone() else {
            continue;
        };
        if !slots.take(frame.rgb.header().stamp.nanos()) {
            continue;
        }
        let wanted = relocalize.swap(false, Ordering::SeqCst);
        let initial = lock(&state).initial.take();
        let prepared = tokio::select! {
            _ = &mut shutdown => break,
            r = request_of(&state, &ros, &frame, &map_id, wanted, initial.as_ref()) => r,
        };
        let (request, base_from_camera, odom_from_base) = match prepared {
            Ok(r) => r,
            Err(why) => {
                if wanted {
                    relocalize.store(true, Ordering::SeqCst);
                }
                let mut s = lock(&state);
                if s.initial.is_none() {
                    s.initial = initial;
                }
                s.stats.skipped += 1;
                s.stats.last_skip = Some(Instant::now());
                if s.stats.skipped.is_power_of_two() {
                    tracing::warn!("frame skipped ({} so far): {why}", s.stats.skipped);
                }
                s.stats.last_reason = why;
                continue;
            }
        };
        let stamp = frame.rgb.header().stamp;
        let asked = Instant::now();
        let result = tokio::select! {
            _ = &mut shutdown => break,
            r = link.localize(request) => r,
        };
        let latency_ms = asked.elapsed().as_secs_f64() * 1e3;
        let r = {
            let mut s = lock(&state);
            s.stats.connected = link.is_open();
            s.stats.refused = link.refused;
            match result {
                Err(why) => {
                    if wanted {
                        relocalize.store(true, Ordering::SeqCst);
                    }
                    if s.initial.is_none() {
                        s.initial = initial;
                    }
                    s.stats.failed += 1;
                    s.stats.last_reason = format!("server: {why}");
                    continue;
                }
                Ok(r) => {
                    s.stats.sent += 1;
                    s.stats.last_latency_ms = latency_ms;
                    s.stats.last_answer = Some(Instant::now());
                    s.stats.map_id = r.map_id.clone();
                    s.stats.map_version = r.map_version.clone();
                    s.stats.last_reason = r.reason.clone();
                    s.stats.last_track = proto::TrackState::try_from(r.track_state)
                        .map_or("UNKNOWN", |t| t.as_str_name())
                        .to_string();
                    r
                }
            }
        };
        let pose = (r.status == proto::Status::Localized as i32)
            .then(|| answer::pose_of(&r))
            .flatten();
        let Some(map_from_camera) = pose else {
            let mut s = lock(&state);
            s.stats.not_localized += 1;
            s.stats.last_status = "NOT_LOCALIZED".into();
            continue;
        };
        let (map_from_base, covariance) =
            answer::base_pose(&map_from_camera, &r.covariance, &base_from_camera);
        let map_from_odom = answer::map_from_odom(&map_from_base, &odom_from_base);
        {
            let mut s = lock(&state);
            s.stats.localized += 1;
            s.stats.last_status = "LOCALIZED".into();
            s.map_from_odom = Some(map_from_odom);
        }
        let message = msgs::PoseWithCovarianceStamped {
            header: msgs::Header {
                stamp,
                frame_id: p.map_frame.clone(),
            },
            pose: msgs::PoseWithCovariance {
                pose: {
                    let t = tf::transform(&map_from_base);
                    msgs::Pose {
                        position: t.translation,
                        orientation: t.rotation,
                    }
                },
                covariance,
            },
        };
        if let Err(e) = pose_pub.async_publish(message).await {
            tracing::warn!("publishing the pose: {e:?}");
        }
        if p.publish_tf {
            let stamp = plus_seconds(stamp, p.transform_tolerance_s);
            let _ = tf_pub
                .async_publish(tf_message(&ros, &map_from_odom, stamp))
                .await;
        }
    }
    tracing::info!("pntr-ros: shutting down");
    Ok(())
}

/// SIGINT or SIGTERM.
async fn shutdown_signal() {
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => futures::future::pending::<()>().await,
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = terminate => {}
    }
}

fn diagnostics(s: &Stats, ros: &RosArgs, addr: &str, up: Duration) -> msgs::DiagnosticArray {
    let recent = s
        .last_answer
        .is_some_and(|t| t.elapsed() < Duration::from_secs(5));
    let skipping = s
        .last_skip
        .is_some_and(|t| t.elapsed() < Duration::from_secs(2));
    let (level, message) = if !s.connected && s.failed > 0 {
        let state = if s.refused { "refuses" } else { "unreachable" };
        (2, format!("pntr-server {addr} {state}: {}", s.last_reason))
    } else if skipping && !recent {
        (2, format!("frames skipped: {}", s.last_reason))
    } else if s.pairs == 0 {
        (
            3,
            format!(
                "no camera frames yet: nothing on {} with depth on {} (stamps within sync_slop_s {} s)",
                ros.resolve(&ros.params.rgb_topic),
                ros.resolve(&ros.params.depth_topic),
                ros.params.sync_slop_s
            ),
        )
    } else if !recent {
        (
            3,
            "no frame answered in the last 5 s (the camera stopped, or the frames are dropped)"
                .to_string(),
        )
    } else if s.last_status == "LOCALIZED" {
        (0, "localized".to_string())
    } else {
        (1, format!("not localized: {}", s.last_reason))
    };
    let kv = |k: &str, v: String| msgs::KeyValue {
        key: k.into(),
        value: v,
    };
    let secs = up.as_secs_f64().max(1e-9);
    msgs::DiagnosticArray {
        header: msgs::Header {
            stamp: Time::now(),
            frame_id: String::new(),
        },
        status: vec![msgs::DiagnosticStatus {
            level,
            name: format!(
                "{}/{}: localization",
                ros.namespace.trim_end_matches('/'),
                ros.node_name
            )
            .trim_start_matches('/')
            .to_string(),
            message,
            hardware_id: addr.to_string(),
            values: vec![
                kv("status", s.last_status.clone()),
                kv("last_reason", s.last_reason.clone()),
                kv("track", s.last_track.clone()),
                kv("frames_paired", s.pairs.to_string()),
                kv("frames_sent", s.sent.to_string()),
                kv("frames_localized", s.localized.to_string()),
                kv("frames_not_localized", s.not_localized.to_string()),
                kv("frames_skipped", s.skipped.to_string()),
                kv("frames_failed", s.failed.to_string()),
                kv(
                    "localized_per_s",
                    format!("{:.2}", s.localized as f64 / secs),
                ),
                kv("latency_ms", format!("{:.1}", s.last_latency_ms)),
                kv("map_id", s.map_id.clone()),
                kv("map_version", s.map_version.clone()),
                kv("connected", s.connected.to_string()),
                kv("rate_hz", ros.params.rate_hz.to_string()),
            ],
        }],
    }
}

#[cfg(test)]
mod tests {
    use super::Slots;

    /// Frames stamped `every_ms` apart for `seconds`: how many take a slot at `rate_hz`.
    fn taken(rate_hz: f64, every_ms: f64, seconds: f64) -> usize {
        let mut s = Slots::new(rate_hz);
        (0..(seconds * 1000.0 / every_ms) as i64)
            .filter(|i| s.take((*i as f64 * every_ms * 1e6) as i64))
            .count()
    }

    #[test]
    fn at_most_rate_hz_and_every_slot_a_camera_fills() {
        // 30 Hz at 4 Hz: one frame per 0.25 s of stamps (the first at 0 s, so 41 in 10 s), never more.
        assert_eq!(taken(4.0, 1000.0 / 30.0, 10.0), 41);
        assert_eq!(taken(4.0, 1000.0 / 30.0, 100.0), 401);
        assert_eq!(taken(5.0, 100.0, 10.0), 50);
        // A camera slower than the rate: every frame.
        assert_eq!(taken(5.0, 300.0, 9.0), 30);
        // Jitter of a few milliseconds does not cost slots.
        let mut s = Slots::new(5.0);
        let n = (0..100)
            .filter(|i| s.take(i * 100_000_000 + if i % 2 == 0 { 3_000_000 } else { -3_000_000 }))
            .count();
        assert_eq!(n, 50);
        // Stamps that go back start afresh.
        let mut s = Slots::new(5.0);
        assert!(s.take(10_000_000_000));
        assert!(s.take(1_000_000_000));
    }
}
