//! The `pntr.v1.Localizer` implementation: resolve the map, decode and check the frame, queue it for
//! a worker, wait for the answer within the client's deadline, and account for it in metrics.
//!
//! The async side never runs the pipeline: it only decodes, validates and waits, so a handful of
//! runtime threads serve any number of connections while the worker pool bounds the CPU work.

use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use pntr_pipeline::odometry::Keyframe;
use pntr_pipeline::pipeline::OUTSIDE_MAP_PREFIX;
use pntr_pipeline::prior::{tracking_heading, tracking_region, Heading, LocalizeOptions, Region};
use tokio::sync::oneshot;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::metadata::{MetadataMap, MetadataValue};
use tonic::service::Interceptor;
use tonic::{Code, Request, Response, Status, Streaming};
use tracing::Instrument;

use crate::decode::{self, Limits};
use crate::engine::{Engine, Job, LoadedMap, Outcome, SubmitError};
use crate::proto;
use crate::telemetry::{
    ANSWERS_BY_MODE, ANSWER_CONFIDENCE, IN_FLIGHT, REQUESTS_TOTAL, STAGE_DURATION, STREAMS_ACTIVE,
};
use crate::wire;

/// Shared state of the service: the engine once loaded, the frame limits, and the permits for
/// decoding frames.
#[derive(Debug)]
pub struct State {
    engine: OnceLock<Arc<Engine>>,
    limits: Limits,
    decoders: Arc<tokio::sync::Semaphore>,
    /// One permit per LocalizeStream open (`--max-streams`): the bound on the tracking states the
    /// server holds at once.
    streams: Arc<tokio::sync::Semaphore>,
    max_streams: usize,
    /// Turns true when the server begins to shut down (open streams then end with UNAVAILABLE).
    stop: tokio::sync::watch::Receiver<bool>,
    /// Held by each map change (MapAdmin, SIGHUP), so changes apply one at a time.
    pub(crate) admin: tokio::sync::Mutex<()>,
    /// The live Foxglove view (`--foxglove`), when on.
    live: OnceLock<crate::visual::Live>,
}

impl State {
    /// A state without an engine yet (every Localize answers UNAVAILABLE until [`State::set_engine`]).
    /// At most `decoders` frames are decoded at once (PNG/JPEG decoding runs on blocking threads, so a
    /// large frame never stalls the async threads that answer health checks and other calls, and the
    /// permits bound the memory that decoded frames can take before the queue admits them).
    /// At most `max_streams` LocalizeStreams are open at once (one more is refused with
    /// RESOURCE_EXHAUSTED). `stop` turns true when the server begins to shut down.
    pub fn new(
        limits: Limits,
        decoders: usize,
        max_streams: usize,
        stop: tokio::sync::watch::Receiver<bool>,
    ) -> Self {
        Self {
            engine: OnceLock::new(),
            limits,
            decoders: Arc::new(tokio::sync::Semaphore::new(decoders.max(1))),
            streams: Arc::new(tokio::sync::Semaphore::new(max_streams.max(1))),
            max_streams: max_streams.max(1),
            stop,
            admin: tokio::sync::Mutex::new(()),
            live: OnceLock::new(),
        }
    }

    /// Attach the live Foxglove view (once; a second is ignored).
    pub fn set_live(&self, live: crate::visual::Live) {
        let _ = self.live.set(live);
    }

    /// The live Foxglove view, when the server has one.
    pub fn live(&self) -> Option<&crate::visual::Live> {
        self.live.get()
    }

    /// Install the loaded engine (once).
    pub fn set_engine(&self, engine: Arc<Engine>) {
        let _ = self.engine.set(engine);
    }

    /// The engine, if loaded.
    pub fn engine(&self) -> Option<&Arc<Engine>> {
        self.engine.get()
    }

    pub(crate) fn loaded(&self) -> Result<&Arc<Engine>, Status> {
        self.engine
            .get()
            .ok_or_else(|| Status::unavailable("the server is still loading its maps and models"))
    }
}

/// When the request reached the service (stamped by [`Gate`]), to measure the client's deadline from.
#[derive(Debug, Clone, Copy)]
struct Arrival(Instant);

/// Checks the bearer token (when one is configured) and stamps the arrival time. Runs before the
/// message is decoded, so an unauthenticated client cannot make the server decode anything.
#[derive(Clone, Default)]
pub struct Gate {
    token: Option<Arc<[u8]>>,
}

impl Gate {
    /// A gate requiring `authorization: Bearer <token>` when `token` is set.
    pub fn new(token: Option<&str>) -> Self {
        Self {
            token: token.map(|t| Arc::from(format!("Bearer {t}").into_bytes())),
        }
    }
}

/// Compare without an early exit, so response time does not reveal how much of a token matched.
pub(crate) fn same(a: &[u8], b: &[u8]) -> bool {
    let mut diff = (a.len() != b.len()) as u8;
    for (i, x) in a.iter().enumerate() {
        diff |= x ^ b.get(i).copied().unwrap_or(!x);
    }
    diff == 0
}

impl Interceptor for Gate {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(want) = &self.token {
            let got = req
                .metadata()
                .get("authorization")
                .map(|v| v.as_bytes())
                .unwrap_or_default();
            if !same(got, want) {
                count("ERROR", Code::Unauthenticated, "");
                return Err(Status::unauthenticated(
                    "missing or invalid bearer token (send `authorization: Bearer <token>` metadata)",
                ));
            }
        }
        req.extensions_mut().insert(Arrival(Instant::now()));
        Ok(req)
    }
}

/// Parse gRPC's `grpc-timeout` header (e.g. `500m`, `2S`, at most 8 digits).
pub fn grpc_timeout(meta: &MetadataMap) -> Option<Duration> {
    let s = meta.get("grpc-timeout")?.to_str().ok()?;
    if s.len() < 2 || s.len() > 9 {
        return None;
    }
    let (num, unit) = s.split_at(s.len() - 1);
    let n: u64 = num.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.checked_mul(3600)?),
        "M" => Duration::from_secs(n.checked_mul(60)?),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

/// The client's deadline. tonic's transport also enforces `grpc-timeout` (answering CANCELLED when it
/// fires); ours is set a few milliseconds earlier so that the client gets DEADLINE_EXCEEDED, the code
/// gRPC specifies.
fn deadline<T>(req: &Request<T>) -> Option<Instant> {
    let t = grpc_timeout(req.metadata())?;
    let arrival = req
        .extensions()
        .get::<Arrival>()
        .map_or_else(Instant::now, |a| a.0);
    let margin = (t / 10).min(Duration::from_millis(5));
    Some(arrival + t - margin)
}

/// The request id: the message's field, else `x-request-id` metadata, else a new one.
fn request_id(field: &str, meta: &MetadataMap) -> Result<String, Status> {
    let given = if field.is_empty() {
        meta.get("x-request-id")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
    } else {
        field
    };
    if given.is_empty() {
        return Ok(format!("{:016x}", rand::random::<u64>()));
    }
    if given.len() > 128 || !given.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(Status::invalid_argument(
            "request_id must be at most 128 printable ASCII characters without spaces",
        ));
    }
    Ok(given.to_string())
}

/// Count a finished request; `map_id` is the map that answered ("" when none was resolved).
fn count(status: &'static str, code: Code, map_id: &str) {
    metrics::counter!(REQUESTS_TOTAL, "status" => status, "code" => code_name(code), "map_id" => map_id.to_string())
        .increment(1);
}

/// Count an answer: LOCALIZED, or NOT_LOCALIZED with its `cause` label
/// ([`pntr_pipeline::pipeline::Cause::name`]).
fn count_answer(r: &proto::LocalizeResponse, map_id: &str) {
    let status = if r.status == proto::Status::Localized as i32 {
        "LOCALIZED"
    } else {
        "NOT_LOCALIZED"
    };
    metrics::histogram!(ANSWER_CONFIDENCE, "status" => status, "map_id" => map_id.to_string())
        .record(r.confidence);
    if r.status == proto::Status::Localized as i32 {
        count("LOCALIZED", Code::Ok, map_id);
    } else {
        let cause = wire::cause_name(r.cause);
        metrics::counter!(REQUESTS_TOTAL, "status" => "NOT_LOCALIZED", "code" => "OK", "cause" => cause, "map_id" => map_id.to_string())
            .increment(1);
    }
}

/// The map id a call names: the message's field, else the `x-pntr-map-id` metadata (set by clients
/// for proxies that route by map), else empty (the server's only map).
fn map_id_of(field: &str, meta: &MetadataMap) -> String {
    if !field.is_empty() {
        return field.to_string();
    }
    meta.get(MAP_ID_HEADER)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string()
}

/// The metadata key that names the map when a message leaves `map_id` empty.
pub const MAP_ID_HEADER: &str = "x-pntr-map-id";

/// gRPC's upper-case code names (as in the spec), for labels.
pub fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "CANCELLED",
        Code::Unknown => "UNKNOWN",
        Code::InvalidArgument => "INVALID_ARGUMENT",
        Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
        Code::NotFound => "NOT_FOUND",
        Code::AlreadyExists => "ALREADY_EXISTS",
        Code::PermissionDenied => "PERMISSION_DENIED",
        Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
        Code::FailedPrecondition => "FAILED_PRECONDITION",
        Code::Aborted => "ABORTED",
        Code::OutOfRange => "OUT_OF_RANGE",
        Code::Unimplemented => "UNIMPLEMENTED",
        Code::Internal => "INTERNAL",
        Code::Unavailable => "UNAVAILABLE",
        Code::DataLoss => "DATA_LOSS",
        Code::Unauthenticated => "UNAUTHENTICATED",
    }
}

/// Keeps `pntr_in_flight_requests` right on every exit path, and counts a request whose caller went
/// away before the answer (tonic drops the handler's future) as `ERROR`/`CANCELLED`.
struct InFlight {
    counted: bool,
    /// The map the request resolved ("" until then).
    map_id: String,
}

impl InFlight {
    fn new() -> Self {
        metrics::gauge!(IN_FLIGHT).increment(1.0);
        Self {
            counted: false,
            map_id: String::new(),
        }
    }

    fn count(&mut self, status: &'static str, code: Code) {
        count(status, code, &self.map_id);
        self.counted = true;
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        metrics::gauge!(IN_FLIGHT).decrement(1.0);
        if !self.counted {
            count("ERROR", Code::Cancelled, &self.map_id);
            tracing::info!("the caller went away before the answer");
        }
    }
}

/// Counts an open `LocalizeStream` for as long as its task lives.
struct StreamGauge;

impl StreamGauge {
    fn new() -> Self {
        metrics::gauge!(STREAMS_ACTIVE).increment(1.0);
        Self
    }
}

impl Drop for StreamGauge {
    fn drop(&mut self) {
        metrics::gauge!(STREAMS_ACTIVE).decrement(1.0);
    }
}

/// A stream re-anchors (tries the map before its keyframe) once its last map fix is this old, seconds.
pub const REANCHOR_AFTER_S: f64 = 0.5;
/// A map fix this long, seconds, after the stream's last LOCALIZED answer starts an unconfirmed track.
pub const RECONFIRM_AFTER_S: f64 = 1.0;
/// A stream follows its keyframe chain for at most this long, seconds, after its last map fix (the
/// chain's length is bounded too: [`pntr_pipeline::odometry::MAX_PATH_M`]).
pub const ODOMETRY_MAX_AGE_S: f64 = 60.0;

/// A map fix with at least this many inliers establishes a stream's track at once; a weaker one
/// (a look-alike room matches a few features, rarely many) waits for a later map fix along the
/// camera's motion to agree: the next re-anchoring, [`REANCHOR_AFTER_S`] later, from a view the
/// camera has moved on to (issue 49: two agreeing 14-18-inlier fixes of a look-alike room 7.8 m
/// away once carried a stream for 7.5 s; re-anchoring after 0.2 s instead, while the camera still
/// saw what the look-alike matched, established it again).
pub const STRONG_FIX_INLIERS: u32 = 40;

/// A later map fix establishes a weak one's track only when it lies within this distance (metres)
/// and angle (degrees) of where the frame's odometry from that track put it
/// ([`pntr_pipeline::pipeline::Localization::track_gap`]).
pub const ESTABLISH_GAP_M: f64 = 0.15;
/// See [`ESTABLISH_GAP_M`].
pub const ESTABLISH_GAP_DEG: f64 = 5.0;
/// When the track's keyframe gives the frame no pose (nothing to compare with), the fix must
/// lie within [`ESTABLISH_GAP_M`] of the track's last pose plus this speed (metres per second) times
/// the time since...
pub const ESTABLISH_SPEED_MPS: f64 = 0.5;
/// ... and within [`ESTABLISH_GAP_DEG`] of its orientation plus this turn rate (degrees per second).
pub const ESTABLISH_TURN_DEG_PER_S: f64 = 45.0;

/// A stream whose frames the map has not matched ([`Verdict::Missed`]) for this long, seconds
/// (capture stamps when the frames carry them), in at least [`OUTSIDE_MAP_FRAMES`] frames, with no
/// LOCALIZED answer between them, is outside the mapped area: its further misses answer
/// OUTSIDE_MAP (issue 49: a robot that starts in an unmapped wing, or whose track the map dropped
/// there, used to answer UNVERIFIED and NO_MATCH frame after frame, which a supervisor cannot tell
/// from a camera that sees nothing).
pub const OUTSIDE_MAP_AFTER_S: f64 = 1.0;
/// See [`OUTSIDE_MAP_AFTER_S`].
pub const OUTSIDE_MAP_FRAMES: u32 = 3;
/// A frame this long, seconds, after the run's last frame starts a new run: where the camera was
/// before such a gap says nothing of where it is now.
pub const OUTSIDE_MAP_MAX_GAP_S: f64 = 2.0;
/// A refusal by verification is a miss when its calibrated confidence (the probability that the
/// best pose found is right) is below this: the map holds no place like the view, rather than one
/// it is unsure of.
pub const MISS_CONFIDENCE: f64 = 0.2;

/// What an answer says of whether the map holds the frame's view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    /// Nothing like it, though the frame was fit to be localized: no candidate registered
    /// (NO_MATCH), verification refused its best pose as unlikely ([`MISS_CONFIDENCE`]), or
    /// odometry carried the camera outside the mapped area (OUTSIDE_MAP).
    Missed,
    /// A place, not sure enough: a refusal at [`MISS_CONFIDENCE`] or more, a look-alike, a weak
    /// fix being re-acquired. A run of misses goes on across such frames (a wing of look-alike
    /// rooms gives many), without counting them.
    Unsure,
    /// A LOCALIZED answer, or a frame that says nothing of the place (BAD_INPUT: the camera may
    /// be blocked): it ends a run of misses.
    Other,
}

impl Verdict {
    fn of(r: &proto::LocalizeResponse) -> Self {
        use proto::NotLocalizedCause as C;
        if r.status == proto::Status::Localized as i32 {
            return Self::Other;
        }
        match C::try_from(r.cause) {
            Ok(C::NoMatch | C::OutsideMap) => Self::Missed,
            Ok(C::Unverified)
                if r.confidence < MISS_CONFIDENCE.min(r.min_confidence)
                    && r.reason.starts_with("verification:") =>
            {
                Self::Missed
            }
            Ok(C::Unverified | C::LookAlike) => Self::Unsure,
            _ => Self::Other,
        }
    }
}

/// The run of misses a stream is in ([`Verdict`]): the map it was against (id and
/// [`LoadedMap::serial`]), when its first miss and its last frame were, how many misses and how many
/// frames since the first.
#[derive(Debug, Default)]
struct Misses {
    map: Option<(String, u64)>,
    since: Option<Moment>,
    last: Option<Moment>,
    missed: u32,
    frames: u32,
}

/// A run of misses long enough to put a stream outside the mapped area: seconds since its first
/// miss, misses, frames.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Run {
    seconds: f64,
    missed: u32,
    frames: u32,
}

impl Misses {
    /// Take answer `r` of map `map` (its id and [`LoadedMap::serial`]; a frame captured at
    /// `stamp_s`): the run, when `r` is a miss that comes [`OUTSIDE_MAP_AFTER_S`] or more after the
    /// run's first and the run holds [`OUTSIDE_MAP_FRAMES`] misses or more. Another map (or a new
    /// version of it), or a frame [`OUTSIDE_MAP_MAX_GAP_S`] after the run's last, starts anew.
    fn after(
        &mut self,
        r: &proto::LocalizeResponse,
        map: (&str, u64),
        stamp_s: Option<f64>,
    ) -> Option<Run> {
        let now = Moment::now(stamp_s);
        let same_map = self
            .map
            .as_ref()
            .is_some_and(|(id, serial)| (id.as_str(), *serial) == map);
        if !same_map
            || self
                .last
                .is_some_and(|t| now.since(&t) > OUTSIDE_MAP_MAX_GAP_S)
        {
            *self = Self {
                map: Some((map.0.to_string(), map.1)),
                ..Self::default()
            };
        }
        self.last = Some(now);
        match Verdict::of(r) {
            Verdict::Other => {
                self.since = None;
                self.missed = 0;
                self.frames = 0;
                None
            }
            Verdict::Unsure => {
                self.frames += self.since.is_some() as u32;
                None
            }
            Verdict::Missed => {
                let since = *self.since.get_or_insert(now);
                self.missed += 1;
                self.frames += 1;
                let seconds = now.since(&since);
                (seconds >= OUTSIDE_MAP_AFTER_S && self.missed >= OUTSIDE_MAP_FRAMES).then_some(
                    Run {
                        seconds,
                        missed: self.missed,
                        frames: self.frames,
                    },
                )
            }
        }
    }
}

/// Say of a missed frame that the stream is outside the mapped area: cause OUTSIDE_MAP, the reason
/// prefixed with [`OUTSIDE_MAP_PREFIX`] and the run's length, the frame's own reason kept after it.
/// An answer that already says so is left as it is.
fn outside_map(r: &mut proto::LocalizeResponse, run: Run) {
    if r.cause == proto::NotLocalizedCause::OutsideMap as i32 {
        return;
    }
    let Run {
        seconds,
        missed,
        frames,
    } = run;
    let counts = if missed == frames {
        format!("the map matched none of the last {frames} frames, each fit to be localized")
    } else {
        format!(
            "the map matched none of {missed} of the last {frames} frames, each fit to be localized, and the others only to places too uncertain to answer"
        )
    };
    r.cause = proto::NotLocalizedCause::OutsideMap as i32;
    r.reason = format!(
        "{OUTSIDE_MAP_PREFIX} no place of the map has matched the camera's view for {seconds:.1} s ({counts}); the stream answers again when the camera is back where the map reaches, and if the robot is in mapped rooms, something in front of the camera hides them (this frame: {})",
        r.reason
    );
}

/// When something happened to a stream: the server's clock, and the capture stamp of the frame
/// (`LocalizeRequest.stamp_s`, seconds on the sensor's clock) when the client sent one.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Moment {
    at: Instant,
    stamp_s: Option<f64>,
}

impl Moment {
    /// Now, for a frame captured at `stamp_s` (when known).
    fn now(stamp_s: Option<f64>) -> Self {
        Self {
            at: Instant::now(),
            stamp_s,
        }
    }

    /// Seconds from `earlier` to this moment: by the capture stamps when both frames carry one
    /// (the camera's own time, however fast the frames were sent or answered), but never less
    /// than [`STAMPED_CLOCK_SHARE`] of the server's clock (stamps that stopped advancing, a client
    /// repeating one stamp, must not keep a track from ever being checked against the map); else
    /// by the server's clock. Never negative.
    fn since(&self, earlier: &Moment) -> f64 {
        let served = self.at.saturating_duration_since(earlier.at).as_secs_f64();
        match (self.stamp_s, earlier.stamp_s) {
            (Some(now), Some(then)) => (now - then).max(served * STAMPED_CLOCK_SHARE),
            _ => served,
        }
    }
}

/// Between stamped frames, elapsed time is at least this share of the server clock's: a replay up
/// to ten times slower than its recording is judged by its stamps alone.
const STAMPED_CLOCK_SHARE: f64 = 0.1;

/// What a stream remembers between frames: where its last LOCALIZED answer put the camera, whether
/// that fix is confirmed, the keyframe the next frame registers against ([`pntr_pipeline::odometry`])
/// and when the chain was last verified against the map. A global fix is confirmed only by a second
/// LOCALIZED answer within the tracking region of the first (two independent retrievals agree), so one
/// look-alike answer cannot start tracking in the wrong place; answers found by tracking or a prior
/// inherit it. One keyframe and the last frame tracked from it (about 1 MB each with XFeat) per open
/// stream, freed with the stream.
#[derive(Clone)]
struct Track {
    map_id: String,
    /// [`LoadedMap::frame`] of the map the track's poses are in.
    frame: u64,
    /// [`LoadedMap::serial`] of the map its keyframe was made on (the keyframe names map images by
    /// index).
    serial: u64,
    position_m: Vector3<f64>,
    rotation: UnitQuaternion<f64>,
    at: Moment,
    confirmed: bool,
    keyframe: Option<Arc<Keyframe>>,
    anchored_at: Moment,
    /// When a frame last tried the map before the keyframe (re-anchoring), since `anchored_at`.
    map_tried_at: Option<Moment>,
    /// Calibrated confidence of the map fix the track rests on.
    confidence: f64,
    /// Whether the track's answers are reported LOCALIZED: it rests on a strong map fix
    /// ([`STRONG_FIX_INLIERS`]) or on a map fix that agreed with the confirmed track carried there
    /// (a re-anchoring). Until then the stream tracks but answers NOT_LOCALIZED (UNVERIFIED).
    established: bool,
    /// The last map answer that verified, was more confident than the track, and was refused for
    /// lying outside the track's bounds.
    challenger: Option<Challenger>,
}

/// A map answer refused because it lay outside a track's bounds (see [`Track::challenged`]).
#[derive(Debug, Clone, Copy)]
struct Challenger {
    position_m: Vector3<f64>,
    rotation: UnitQuaternion<f64>,
    confidence: f64,
    at: Moment,
}

/// What the stream needs from an answer besides the response: the next keyframe, and whether the
/// pose came from the keyframe rather than the map.
#[derive(Debug, Default)]
struct Followup {
    /// The convention the caller wants the answer in, and the answering map's own frames.
    convention: proto::FrameConvention,
    frames: wire::MapFrames,
    keyframe: Option<Arc<Keyframe>>,
    odometry: bool,
    /// The map's answer refused for lying outside the track's bounds: pose (map frame) and confidence.
    off_track: Option<(Isometry3<f64>, f64)>,
    /// Where odometry put the camera when that was outside the mapped area (NOT_LOCALIZED, cause
    /// OUTSIDE_MAP): the track follows it (map frame), so a look-alike room elsewhere stays off
    /// track and the stream answers again when the camera is back in the map.
    dead_reckoned: Option<Isometry3<f64>>,
    /// [`LoadedMap::frame`] and [`LoadedMap::serial`] of the map that answered.
    frame: u64,
    serial: u64,
    /// The map contradicted the stream's track ([`pntr_pipeline::pipeline::Localization::track_lost`]): it is dropped before
    /// this answer is taken.
    track_lost: bool,
    /// [`pntr_pipeline::pipeline::Localization::track_gap`]: how far a re-anchoring map answer lay from the frame's own
    /// odometry pose (metres, degrees).
    track_gap: Option<(f64, f64)>,
    /// [`pntr_pipeline::pipeline::Localization::track_slipped`]: the map's views judged that the
    /// track had slipped and this map answer anchors it.
    track_slipped: bool,
    /// The frame's capture stamp (`LocalizeRequest.stamp_s`), when it carries one.
    stamp_s: Option<f64>,
}

/// What the stream's state offers the next frame (all empty for a unary call).
#[derive(Debug, Default)]
struct Tracking {
    /// The frame belongs to a stream (which keeps a keyframe).
    stream: bool,
    region: Option<Region>,
    heading: Option<Heading>,
    keyframe: Option<Arc<Keyframe>>,
    map_first: bool,
}

impl Track {
    /// The state after answer `r`, given the state before (`None` for an answer that is not
    /// LOCALIZED: the last fix stays).
    fn after(previous: Option<&Track>, r: &proto::LocalizeResponse, f: Followup) -> Option<Self> {
        if r.status != proto::Status::Localized as i32 {
            return previous.and_then(|p| p.dead_reckoned(r, f));
        }
        let pose = wire::pose(r.pose.as_ref())?;
        let position_m = pose.translation.vector;
        let rotation = pose.rotation;
        let global = r.mode == proto::Mode::Global as i32;
        let same_map = previous.is_some_and(|p| p.map_id == r.map_id);
        let now = Moment::now(f.stamp_s);
        let agrees = same_map
            && previous.is_some_and(|p| {
                let elapsed_s = now.since(&p.at);
                tracking_region(p.position_m, elapsed_s)
                    .is_some_and(|region| region.contains(&position_m))
                    && tracking_heading(p.rotation, elapsed_s)
                        .exceeded_by(&rotation)
                        .is_none()
            });
        let recent = same_map && previous.is_some_and(|p| now.since(&p.at) <= RECONFIRM_AFTER_S);
        Some(Self {
            map_id: r.map_id.clone(),
            frame: f.frame,
            serial: f.serial,
            position_m,
            rotation,
            at: now,
            // Odometry continues the chain it registered against. A map fix inherits the track's
            // confirmation only right after its last answer: after a gap the tracking region has
            // grown enough to hold look-alikes, so the fix must be confirmed again by a second one.
            confirmed: if f.odometry {
                previous.is_none_or(|p| p.confirmed)
            } else if !recent {
                false
            } else if global {
                agrees
            } else {
                previous.is_none_or(|p| p.confirmed)
            },
            // A weak fix is established by a later one only when that one follows the camera's
            // motion: the frame's own odometry pose from the first lies within a few centimetres
            // of it (issue 49: a look-alike's weak fixes lay 0.3 m apart, near enough for the
            // tracking region, not for the motion between them).
            established: if f.odometry {
                previous.is_some_and(|p| p.established)
            } else {
                let follows = match f.track_gap {
                    Some((m, deg)) => m <= ESTABLISH_GAP_M && deg <= ESTABLISH_GAP_DEG,
                    // The keyframe gave the frame no pose: the fix must lie where the camera can
                    // have moved since the track's last pose, at a robot's pace.
                    None => previous.is_some_and(|p| {
                        let dt = now.since(&p.at);
                        (position_m - p.position_m).norm()
                            <= ESTABLISH_GAP_M + ESTABLISH_SPEED_MPS * dt
                            && p.rotation.angle_to(&rotation).to_degrees()
                                <= ESTABLISH_GAP_DEG + ESTABLISH_TURN_DEG_PER_S * dt
                    }),
                };
                // A fix the map's views prefer to the track's own pose (the track slipped) keeps
                // an established track established, where it now lies.
                r.inliers >= STRONG_FIX_INLIERS
                    || (recent && agrees && follows && previous.is_some_and(|p| p.confirmed))
                    || (recent && f.track_slipped && previous.is_some_and(|p| p.established))
            },
            keyframe: f.keyframe,
            anchored_at: match previous {
                Some(p) if f.odometry && same_map => p.anchored_at,
                _ => now,
            },
            map_tried_at: previous
                .filter(|_| f.odometry && same_map)
                .and_then(|p| p.map_tried_at),
            confidence: r.confidence,
            challenger: previous
                .filter(|_| same_map)
                .and_then(|p| p.challenger)
                .filter(|c| now.since(&c.at) <= RECONFIRM_AFTER_S),
        })
    }

    /// The track moved to where odometry put the camera outside the mapped area (`f.dead_reckoned`,
    /// answer `r` NOT_LOCALIZED), keeping its confirmation, its anchoring time (the chain's age
    /// bounds how far it is followed) and the fix's confidence; `None` for any other refusal (the
    /// last fix stays).
    fn dead_reckoned(&self, r: &proto::LocalizeResponse, f: Followup) -> Option<Track> {
        let pose = f.dead_reckoned?;
        if r.map_id != self.map_id || f.serial != self.serial {
            return None;
        }
        Some(Track {
            position_m: pose.translation.vector,
            rotation: pose.rotation,
            at: Moment::now(f.stamp_s),
            keyframe: f.keyframe,
            ..self.clone()
        })
    }

    /// A map answer that verified but lay outside the track's bounds (`pose`, map frame, with its
    /// calibrated `confidence`). A track rests on two agreeing map fixes; when two answers more
    /// confident than the track's fix agree with each other (within a second, inside each other's
    /// tracking bounds) but not with the track, the track is the look-alike: the new track starts
    /// there, confirmed (two agreeing fixes, as any track), without a keyframe. A track that is not
    /// established yet rests on one weak fix: one such answer replaces it, unconfirmed, as a first
    /// fix would start a track. Returns that track; otherwise remembers the answer and returns
    /// `None`.
    fn challenged(
        &mut self,
        pose: &Isometry3<f64>,
        confidence: f64,
        stamp_s: Option<f64>,
    ) -> Option<Track> {
        if confidence <= self.confidence {
            return None;
        }
        let now = Moment::now(stamp_s);
        if !self.established {
            return Some(Track {
                map_id: self.map_id.clone(),
                frame: self.frame,
                serial: self.serial,
                position_m: pose.translation.vector,
                rotation: pose.rotation,
                at: now,
                confirmed: false,
                established: false,
                keyframe: None,
                anchored_at: now,
                map_tried_at: None,
                confidence,
                challenger: None,
            });
        }
        let c = Challenger {
            position_m: pose.translation.vector,
            rotation: pose.rotation,
            confidence,
            at: now,
        };
        let agrees = self.challenger.is_some_and(|p| {
            let elapsed_s = now.since(&p.at);
            elapsed_s <= RECONFIRM_AFTER_S
                && tracking_region(p.position_m, elapsed_s)
                    .is_some_and(|region| region.contains(&c.position_m))
                && tracking_heading(p.rotation, elapsed_s)
                    .exceeded_by(&c.rotation)
                    .is_none()
        });
        if !agrees {
            self.challenger = Some(c);
            return None;
        }
        let earlier = self.challenger.take().map_or(confidence, |p| p.confidence);
        Some(Track {
            map_id: self.map_id.clone(),
            frame: self.frame,
            serial: self.serial,
            position_m: c.position_m,
            rotation: c.rotation,
            at: now,
            confirmed: true,
            established: true,
            keyframe: None,
            anchored_at: now,
            map_tried_at: None,
            confidence: confidence.min(earlier),
            challenger: None,
        })
    }

    /// What the next frame of map `map_id` (empty: the server's only map) tracks with: nothing before
    /// the fix is confirmed; the keyframe while the chain's last map fix is younger than
    /// [`ODOMETRY_MAX_AGE_S`]; the map first once it is older than [`REANCHOR_AFTER_S`], at most once
    /// per [`REANCHOR_AFTER_S`] (a place the map does not answer costs a map search only on every
    /// few frames).
    /// `stamp_s`: the next frame's capture stamp, when it carries one.
    fn next(&self, map_id: &str, stamp_s: Option<f64>) -> Tracking {
        if !self.confirmed || (!map_id.is_empty() && map_id != self.map_id) {
            return Tracking {
                stream: true,
                ..Tracking::default()
            };
        }
        let now = Moment::now(stamp_s);
        let anchor_age_s = now.since(&self.anchored_at);
        let elapsed_s = now.since(&self.at);

        Tracking {
            stream: true,
            region: tracking_region(self.position_m, elapsed_s),
            heading: Some(tracking_heading(self.rotation, elapsed_s)),
            keyframe: self
                .keyframe
                .clone()
                .filter(|_| anchor_age_s <= ODOMETRY_MAX_AGE_S),
            map_first: anchor_age_s >= REANCHOR_AFTER_S
                && self
                    .map_tried_at
                    .is_none_or(|t| now.since(&t) >= REANCHOR_AFTER_S),
        }
    }
}

/// The Localizer service.
#[derive(Debug, Clone)]
pub struct LocalizerService {
    state: Arc<State>,
}

impl LocalizerService {
    /// A service over `state`.
    pub fn new(state: Arc<State>) -> Self {
        Self { state }
    }

    /// Localize one frame end to end, recording metrics; never panics.
    /// `map`: the map the stream resolved for this frame (`None`: resolve the request's map_id).
    async fn one(
        &self,
        msg: proto::LocalizeRequest,
        map: Option<Arc<LoadedMap>>,
        request_id: String,
        deadline: Option<Instant>,
        tracking: Tracking,
    ) -> Result<(proto::LocalizeResponse, Followup), Status> {
        let mut in_flight = InFlight::new();
        let stream = tracking.stream;
        let span = tracing::info_span!("localize", request_id = %request_id, map_id = tracing::field::Empty);
        let result = self
            .run(msg, map, deadline, tracking, span.clone(), &mut in_flight)
            .instrument(span.clone())
            .await;
        let _entered = span.enter();
        match &result {
            // A stream's answer is counted once its state has settled it (`count_answer`).
            Ok(_) if stream => in_flight.counted = true,
            Ok((r, _)) => {
                count_answer(r, &in_flight.map_id);
                // Counted: the guard must not count it again as a caller that went away.
                in_flight.counted = true;
            }
            Err(e) => {
                in_flight.count("ERROR", e.code());
                if e.code() == Code::Internal {
                    tracing::error!(code = ?e.code(), message = e.message(), "request failed");
                } else {
                    tracing::info!(code = ?e.code(), message = e.message(), "request refused");
                }
            }
        }
        result
    }

    async fn run(
        &self,
        mut msg: proto::LocalizeRequest,
        map: Option<Arc<LoadedMap>>,
        deadline: Option<Instant>,
        tracking: Tracking,
        span: tracing::Span,
        in_flight: &mut InFlight,
    ) -> Result<(proto::LocalizeResponse, Followup), Status> {
        let engine = self.state.loaded()?.clone();
        // Resolved once: the whole request runs on this map, whatever MapAdmin swaps meanwhile.
        let lm = match map {
            Some(m) => m,
            None => engine.resolve(&msg.map_id)?,
        };
        in_flight.map_id = lm.id.clone();
        let convention = decode::frame_convention(msg.frame_convention, engine.frame_convention)?;
        let frames = wire::MapFrames::of(&lm.map.header);
        if let Some(prior) = msg.prior.as_mut() {
            wire::prior_to_map(prior, convention, frames);
        }
        // The caller's prior wins over the stream's own state (its region and its keyframe); a
        // stream's LOCALIZED answer still leaves a keyframe for the next frame.
        let options = match (decode::prior(&msg)?, tracking.region) {
            (Some(region), _) => LocalizeOptions {
                want_keyframe: tracking.stream,
                ..LocalizeOptions::prior(region)
            },
            (None, Some(region)) => LocalizeOptions {
                heading: tracking.heading,
                keyframe: tracking.keyframe,
                map_first: tracking.map_first,
                want_keyframe: tracking.stream,
                ..LocalizeOptions::tracking(region)
            },
            (None, None) => LocalizeOptions {
                want_keyframe: tracking.stream,
                ..LocalizeOptions::default()
            },
        };
        let map_id = lm.id.clone();
        span.record("map_id", map_id.as_str());
        let permit = self
            .state
            .decoders
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Status::unavailable("the server is shutting down"))?;
        let limits = self.state.limits;
        let request_id = msg.request_id.clone();
        // The permit travels with the decoding, which finishes even if the caller leaves meanwhile.
        let query = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            decode::query(&msg, &limits)
        })
        .await
        .map_err(|e| {
            tracing::error!(error = %e, "decoding the frame failed");
            Status::internal("internal error while decoding the frame (logged)")
        })??;
        // The frame as the live view shows it, kept only while someone watches (its image only
        // when one is due: at most 15 a second).
        let watched = self.state.live().filter(|l| l.view().wanted()).map(|l| {
            (
                l,
                l.claim_image().then(|| query.rgb.clone()),
                query.intrinsics,
            )
        });
        let (tx, rx) = oneshot::channel();
        let job = Job {
            map: lm.clone(),
            query,
            options,
            deadline,
            enqueued: Instant::now(),
            span,
            reply: tx,
        };
        match engine.submit(job) {
            Ok(()) => {}
            Err(SubmitError::Full) => {
                return Err(Status::resource_exhausted(format!(
                    "server busy: {} requests already wait for {} workers; retry with back-off",
                    engine.queue, engine.workers
                )))
            }
            Err(SubmitError::Closed) => {
                return Err(Status::unavailable("the server is shutting down"))
            }
        }
        let outcome = match deadline {
            Some(d) => match tokio::time::timeout_at(d.into(), rx).await {
                Ok(r) => r,
                Err(_) => {
                    return Err(Status::deadline_exceeded(
                        "the deadline passed before the frame was localized",
                    ))
                }
            },
            None => rx.await,
        };
        let outcome = outcome.map_err(|_| Status::internal("the worker dropped the request"))?;
        let (loc, queued) = match outcome {
            Outcome::Done { result, queued } => (result.map_err(decode::status_of)?, queued),
            Outcome::Expired { queued } => {
                metrics::histogram!(STAGE_DURATION, "stage" => "queue", "map_id" => lm.id.clone())
                    .record(queued.as_secs_f64());
                return Err(Status::deadline_exceeded(format!(
                    "the deadline passed after {:.0} ms in the queue; the frame was not processed",
                    queued.as_secs_f64() * 1e3
                )));
            }
            Outcome::Panicked { .. } => {
                return Err(Status::internal("internal error while localizing (logged)"))
            }
        };
        let t = &loc.times;
        metrics::counter!(ANSWERS_BY_MODE, "mode" => loc.mode.name(), "map_id" => lm.id.clone())
            .increment(1);
        let stages = crate::engine::stage_seconds(&loc, queued);
        let m = &lm.map;
        let localized = loc.status == pntr_pipeline::pipeline::Status::Localized;
        let matched = loc.image.filter(|_| localized).map(|i| &m.images[i]);
        tracing::info!(
            status = if localized {
                "LOCALIZED"
            } else {
                "NOT_LOCALIZED"
            },
            inliers = loc.inliers,
            total_ms = t.total * 1e3,
            queue_ms = queued.as_secs_f64() * 1e3,
            "localized"
        );
        let response = proto::LocalizeResponse {
            status: if localized {
                proto::Status::Localized
            } else {
                proto::Status::NotLocalized
            } as i32,
            pose: loc.pose.as_ref().map(wire::to_proto_pose),
            confidence: loc.confidence,
            inliers: loc.inliers as u32,
            matched_image_id: matched.map(|im| im.id.clone()).unwrap_or_default(),
            timings: stages
                .iter()
                .map(|&(stage, seconds)| proto::StageTiming {
                    stage: stage.into(),
                    seconds,
                })
                .collect(),
            map_id,
            reason: loc.reason.clone().unwrap_or_default(),
            retrieved_image_ids: loc
                .retrieved
                .iter()
                .filter_map(|h| m.images.get(h.id).map(|im| im.id.clone()))
                .collect(),
            matched_point: matched.map_or(0, |im| im.point),
            request_id: String::new(),
            covariance: if localized {
                loc.covariance.map(|c| c.to_vec()).unwrap_or_default()
            } else {
                Vec::new()
            },
            min_confidence: lm.min_confidence,
            mode: wire::mode_message(loc.mode) as i32,
            map_version: lm.version.label.clone(),
            // Set at the edge, once the stream's state has taken the map-frame pose.
            frame_convention: proto::FrameConvention::Map as i32,
            cause: wire::cause_message(loc.cause.filter(|_| !localized)) as i32,
        };
        if let Some((live, rgb, k)) = watched {
            // Handed to the live view's thread; drawing never holds up the answer.
            live.show(crate::visual::Shown {
                time_s: std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0.0, |d| d.as_secs_f64()),
                rgb,
                intrinsics: k,
                request_id: request_id.clone(),
                map_id: response.map_id.clone(),
                map_version: response.map_version.clone(),
                status: if localized {
                    "LOCALIZED"
                } else {
                    "NOT_LOCALIZED"
                },
                reason: response.reason.clone(),
                confidence: response.confidence,
                inliers: response.inliers,
                mode: loc.mode.name(),
                matched_image_id: response.matched_image_id.clone(),
                pose: loc
                    .pose
                    .as_ref()
                    .filter(|_| localized)
                    .map(|p| frames.pose_to_ros(p)),
                covariance: frames.covariance_to_ros(&response.covariance),
            });
        }
        let outside_map = !localized
            && loc.odometry
            && loc.cause == Some(pntr_pipeline::pipeline::Cause::OutsideMap);
        let followup = Followup {
            convention,
            frames,
            keyframe: loc.keyframe.clone().filter(|_| localized || outside_map),
            odometry: loc.odometry,
            off_track: loc.off_track,
            dead_reckoned: loc.estimate.filter(|_| outside_map),
            frame: lm.frame,
            serial: lm.serial,
            track_lost: loc.track_lost,
            track_gap: loc.track_gap,
            track_slipped: loc.track_slipped,
            stamp_s: None,
        };
        release(lm);
        Ok((response, followup))
    }
}

/// Turn a LOCALIZED stream answer of a track that is not established ([`Track::established`]) into
/// NOT_LOCALIZED (cause UNVERIFIED), saying what it waits for.
fn provisional(r: &mut proto::LocalizeResponse, t: &Track) {
    if r.status != proto::Status::Localized as i32 {
        return;
    }
    r.status = proto::Status::NotLocalized as i32;
    r.cause = proto::NotLocalizedCause::Unverified as i32;
    r.reason = format!(
        "re-acquiring: the stream's map fix had fewer than {STRONG_FIX_INLIERS} inliers, so it is followed but not answered until a later map fix along the camera's motion agrees with it (a look-alike room often does not); {}",
        if t.confirmed {
            "two fixes agree, waiting for the map to re-anchor the track"
        } else {
            "waiting for a second fix"
        }
    );
    r.pose = None;
    r.covariance.clear();
    r.matched_image_id.clear();
    r.matched_point = 0;
}

/// Turn the answer of a frame whose map answer moved the stream's track ([`Track::challenged`])
/// into NOT_LOCALIZED (cause LOOK_ALIKE): its pose is the old track's, which the map has just shown
/// to be the look-alike; the next frame answers from where the track moved.
fn superseded(r: &mut proto::LocalizeResponse, established: bool) {
    if r.status != proto::Status::Localized as i32 {
        return;
    }
    r.status = proto::Status::NotLocalized as i32;
    r.cause = proto::NotLocalizedCause::LookAlike as i32;
    r.reason = if established {
        "tracking: two confident map answers agreed on another pose than the track's, so the track was a look-alike and moves to them; the next frame answers from there"
    } else {
        "re-acquiring: a map answer more confident than the track's weak fix lies elsewhere, so the track starts again from it"
    }
    .into();
    r.pose = None;
    r.covariance.clear();
    r.matched_image_id.clear();
    r.matched_point = 0;
}

/// Drop a request's hold on its map; when it was the last (the map was replaced or unloaded while
/// the request ran), the map is freed on a blocking thread, not on the async one.
fn release(map: Arc<LoadedMap>) {
    if Arc::strong_count(&map) == 1 {
        tokio::task::spawn_blocking(move || drop(map));
    }
}

fn with_request_id<T>(mut r: Response<T>, id: &str) -> Response<T> {
    if let Ok(v) = MetadataValue::try_from(id) {
        r.metadata_mut().insert("x-request-id", v);
    }
    r
}

type ResponseStream = Pin<Box<dyn Stream<Item = Result<proto::LocalizeResponse, Status>> + Send>>;

#[tonic::async_trait]
impl proto::localizer_server::Localizer for LocalizerService {
    async fn localize(
        &self,
        request: Request<proto::LocalizeRequest>,
    ) -> Result<Response<proto::LocalizeResponse>, Status> {
        let deadline = deadline(&request);
        let meta = request.metadata().clone();
        let mut msg = request.into_inner();
        msg.map_id = map_id_of(&msg.map_id, &meta);
        let id = match request_id(&msg.request_id, &meta) {
            Ok(id) => id,
            Err(e) => {
                count("ERROR", e.code(), "");
                return Err(e);
            }
        };
        let mut out = self
            .one(msg, None, id.clone(), deadline, Tracking::default())
            .await
            .map(|(mut r, f)| {
                wire::answer_in(&mut r, f.convention, f.frames);
                r
            })
            .map_err(|mut e| {
                if let Ok(v) = MetadataValue::try_from(id.as_str()) {
                    e.metadata_mut().insert("x-request-id", v);
                }
                e
            })?;
        out.request_id = id.clone();
        Ok(with_request_id(Response::new(out), &id))
    }

    type LocalizeStreamStream = ResponseStream;

    async fn localize_stream(
        &self,
        request: Request<Streaming<proto::LocalizeRequest>>,
    ) -> Result<Response<Self::LocalizeStreamStream>, Status> {
        let deadline = deadline(&request);
        let meta = request.metadata().clone();
        let stream_id = request_id("", &meta)?;
        let span = tracing::info_span!("localize_stream", stream_id = %stream_id);
        let reply_id = stream_id.clone();
        // The stream's slot, held until its task ends (with its tracking state).
        let Ok(slot) = self.state.streams.clone().try_acquire_owned() else {
            count("ERROR", Code::ResourceExhausted, "");
            return Err(Status::resource_exhausted(format!(
                "server busy: {} LocalizeStreams are open, the most this server holds (--max-streams): retry after a back-off, or on another replica",
                self.state.max_streams
            )));
        };
        let mut input = request.into_inner();
        let (tx, rx) = tokio::sync::mpsc::channel(2);
        let this = self.clone();
        let mut stop = self.state.stop.clone();
        tokio::spawn(
            async move {
                let _open = StreamGauge::new();
                // Dropped before the gauge (reverse order): once the gauge says a stream ended, its
                // slot is free.
                let _slot = slot;
                let mut n = 0u64;
                // Tracking state, the whole of what a stream keeps: the last verified position and
                // the keyframe.
                let mut track: Option<Track> = None;
                // The stamp of the stream's last stamped frame.
                let mut last_stamp: Option<f64> = None;
                // The frames the map has not matched, one after another.
                let mut misses = Misses::default();
                loop {
                    // A shutdown ends the stream between frames (the transport has sent GOAWAY
                    // by then), so the robot reconnects at once instead of at the drain's end.
                    let next = tokio::select! {
                        m = input.message() => m,
                        _ = crate::server::stopped(&mut stop) => {
                            count("ERROR", Code::Unavailable, "");
                            let _ = tx.send(Err(Status::unavailable(
                                "the server is shutting down: reconnect (to another replica when there is one)",
                            ))).await;
                            break;
                        }
                    };
                    let mut msg = match next {
                        Ok(Some(m)) => m,
                        Ok(None) => break,
                        Err(e) => {
                            tracing::debug!(error = %e, "stream ended by the client");
                            break;
                        }
                    };
                    n += 1;
                    msg.map_id = map_id_of(&msg.map_id, &meta);
                    let id = if msg.request_id.is_empty() {
                        Ok(format!("{stream_id}-{n}"))
                    } else {
                        request_id(&msg.request_id, &MetadataMap::new())
                    };
                    // The frame's map, resolved once. After a replacement, a track carries over
                    // only onto a map in the same frame, and without its keyframe (whose map image
                    // indices belonged to the old map).
                    let map = match this.state.loaded().and_then(|e| e.resolve(&msg.map_id)) {
                        Ok(m) => m,
                        Err(e) => {
                            count("ERROR", e.code(), "");
                            let _ = tx.send(Err(in_stream(e, n, &msg.request_id))).await;
                            break;
                        }
                    };
                    if let Some(t) = track.as_mut().filter(|t| t.map_id == map.id) {
                        if t.frame != map.frame {
                            tracing::info!(map_id = %map.id, version = %map.version.label,
                                "the map was replaced by one in another frame; the track starts afresh");
                            track = None;
                        } else if t.serial != map.serial {
                            tracing::info!(map_id = %map.id, version = %map.version.label,
                                "the map was replaced by one in the same frame; the track carries over");
                            t.keyframe = None;
                            t.serial = map.serial;
                        }
                    }
                    let stamp_s = match decode::stamp(msg.stamp_s) {
                        Ok(s) => s,
                        Err(e) => {
                            count("ERROR", e.code(), &map.id);
                            let _ = tx.send(Err(in_stream(e, n, &msg.request_id))).await;
                            break;
                        }
                    };
                    // Stamps that go back belong to a recording started again: where the camera
                    // was says nothing about where it is now.
                    if let (Some(then), Some(now)) = (last_stamp, stamp_s) {
                        if now < then {
                            misses = Misses::default();
                        }
                        if now < then && track.is_some() {
                            tracing::info!(from = then, to = now,
                                "the stream's stamps went back; tracking starts afresh");
                            track = None;
                        }
                    }
                    last_stamp = stamp_s.or(last_stamp);
                    // A relocalizing frame is localized globally, as a unary call would be.
                    let relocalize = msg.relocalize;
                    let tracking = match &mut track {
                        _ if msg.relocalize => Tracking::default(),
                        Some(t) => {
                            let next = t.next(&msg.map_id, stamp_s);
                            if next.map_first {
                                t.map_tried_at = Some(Moment::now(stamp_s));
                            }
                            next
                        }
                        None => Tracking {
                            stream: true,
                            ..Tracking::default()
                        },
                    };
                    let map_first = tracking.map_first;
                    let sent_id = msg.request_id.clone();
                    let map_key = (map.id.clone(), map.serial);
                    let result =
                        match id {
                            Ok(id) => this.one(msg, Some(map), id.clone(), deadline, tracking).await.map(
                                |(mut r, f)| {
                                    r.request_id = id;
                                    (r, f)
                                },
                            ),
                            Err(e) => {
                                count("ERROR", e.code(), &map.id);
                                Err(e)
                            }
                        };
                    let result = result.map(|(mut r, mut f)| {
                        f.stamp_s = stamp_s;
                        let off_track = f.off_track;
                        let odometry = f.odometry;
                        let gap = f.track_gap;
                        if f.track_lost {
                            tracing::info!("the map contradicted the stream's track; it is dropped");
                            track = None;
                        }
                        let (convention, frames) = (f.convention, f.frames);
                        if let Some(t) = Track::after(track.as_ref(), &r, f) {
                            track = Some(t);
                        }
                        if let (Some(t), Some((pose, confidence))) = (track.as_mut(), off_track) {
                            if let Some(moved) = t.challenged(&pose, confidence, stamp_s) {
                                tracing::info!(
                                    from = ?t.position_m.as_slice(),
                                    to = ?moved.position_m.as_slice(),
                                    "map answers outside the track moved it"
                                );
                                superseded(&mut r, t.established);
                                track = Some(moved);
                            }
                        }
                        tracing::debug!(
                            frame = n,
                            status = r.status,
                            mode = r.mode,
                            inliers = r.inliers,
                            confidence = r.confidence,
                            odometry = odometry,
                            map_first = map_first,
                            gap = ?gap,
                            off_track = ?off_track.map(|(p, c)| (p.translation.vector.as_slice().to_vec(), c)),
                            track = ?track.as_ref().map(|t| (t.position_m.as_slice().to_vec(), t.confirmed, t.established, t.confidence, t.challenger.is_some())),
                            "stream state"
                        );
                        // A track that is not established yet tracks but does not answer (a
                        // relocalizing frame is answered as a unary call would be).
                        if let Some(t) = track.as_ref().filter(|t| !t.established && !relocalize) {
                            provisional(&mut r, t);
                        }
                        // A relocalizing frame is answered as a unary call would be, and what
                        // came before it says nothing of where the camera is now.
                        if relocalize {
                            misses = Misses::default();
                        } else if let Some(run) = misses.after(&r, (&map_key.0, map_key.1), stamp_s) {
                            outside_map(&mut r, run);
                        }
                        count_answer(&r, &r.map_id);
                        // The track keeps map-frame poses; the caller gets its convention.
                        wire::answer_in(&mut r, convention, frames);
                        r
                    });
                    let result = result.map_err(|e| in_stream(e, n, &sent_id));
                    let failed = result.is_err();
                    if tx.send(result).await.is_err() || failed {
                        break; // the client went away, or an error ends the stream
                    }
                }
            }
            .instrument(span),
        );
        Ok(with_request_id(
            Response::new(Box::pin(ReceiverStream::new(rx)) as ResponseStream),
            &reply_id,
        ))
    }

    async fn get_map_info(
        &self,
        request: Request<proto::GetMapInfoRequest>,
    ) -> Result<Response<proto::MapInfo>, Status> {
        let engine = self.state.loaded()?;
        let lm = engine.resolve(&map_id_of(&request.get_ref().map_id, request.metadata()))?;
        let h = &lm.map.header;
        Ok(Response::new(proto::MapInfo {
            map_id: lm.id.clone(),
            images: lm.map.images.len() as u32,
            points: lm.points as u32,
            scenes: h.scenes.clone(),
            preset: lm.preset.name.clone(),
            built_preset: h.preset.name.clone(),
            extractor: lm.preset.extractor.clone(),
            extractor_engine: lm.extractor_engine.to_string(),
            matcher: lm.preset.matcher.clone(),
            global_descriptor: h.preset.global.clone(),
            camera_axes: h.camera_axes.clone(),
            up_axis: h.up_axis.clone(),
            intrinsics: Some(crate::wire::intrinsics_message(&h.intrinsics)),
            image_width: h.intrinsics.width,
            image_height: h.intrinsics.height,
            build_seconds: h.build_seconds,
            loaded_map_ids: engine.maps().iter().map(|m| m.id.clone()).collect(),
            version: lm.version.label.clone(),
            built_at: lm.version.built_at.clone(),
            ros_from_map: Some(wire::MapFrames::of(h).ros_from_map()),
            frame_convention: engine.frame_convention as i32,
            calibration: Some(calibration_info(&lm)),
        }))
    }
}

/// What GetMapInfo says about the calibration a loaded map's answers use.
pub(crate) fn calibration_info(lm: &LoadedMap) -> proto::CalibrationInfo {
    use pntr_pipeline::calibration::{Calibration, CalibrationSource};
    let own = lm.map.header.calibration.as_ref();
    let mut info = proto::CalibrationInfo {
        source: lm.calibration_source.name().into(),
        threshold: lm.min_confidence,
        ..Default::default()
    };
    match (lm.calibration_source, own) {
        (CalibrationSource::Map, Some(c)) => {
            info.fitted_on = c.calibration.fitted_on.datasets.clone();
            info.expected_precision = c.expected_precision;
            info.negatives = c.negatives as u32;
            info.false_positives = c.false_positives as u32;
            info.regions = c.regions as u32;
            info.stale = lm.calibration_stale;
        }
        (CalibrationSource::Shipped, _) => {
            info.fitted_on = Calibration::embedded().fitted_on.datasets;
        }
        _ => {}
    }
    info
}

/// A stream's error `e` naming the frame it answers: its place in the stream (the first is 1) and
/// the `request_id` the client gave it, when it gave a valid one ([`request_id`]: one refused for
/// its length or characters is not echoed), so a robot's log shows which frame was refused (the
/// error ends the stream). The code and metadata stay `e`'s.
fn in_stream(e: Status, n: u64, request_id: &str) -> Status {
    let valid = !request_id.is_empty()
        && request_id.len() <= 128
        && request_id.bytes().all(|b| b.is_ascii_graphic());
    let id = if valid {
        format!(", request_id {request_id:?}")
    } else {
        String::new()
    };
    Status::with_metadata(
        e.code(),
        format!(
            "frame {n} of this stream (the first is 1{id}): {}",
            e.message()
        ),
        e.metadata().clone(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timeouts_parse() {
        let mut m = MetadataMap::new();
        assert_eq!(grpc_timeout(&m), None);
        for (s, d) in [
            ("500m", Duration::from_millis(500)),
            ("2S", Duration::from_secs(2)),
            ("1H", Duration::from_secs(3600)),
            ("7u", Duration::from_micros(7)),
        ] {
            m.insert("grpc-timeout", s.parse().unwrap());
            assert_eq!(grpc_timeout(&m), Some(d), "{s}");
        }
        for s in ["", "5", "m", "123456789S", "5x", "-5S"] {
            m.insert("grpc-timeout", s.parse().unwrap());
            assert_eq!(grpc_timeout(&m), None, "{s}");
        }
    }

    #[test]
    fn token_comparison() {
        assert!(same(b"Bearer abc", b"Bearer abc"));
        assert!(!same(b"Bearer abd", b"Bearer abc"));
        assert!(!same(b"Bearer ab", b"Bearer abc"));
        assert!(!same(b"Bearer abcd", b"Bearer abc"));
        assert!(!same(b"", b"Bearer abc"));
        let mut g = Gate::new(Some("abc"));
        let e = g.call(Request::new(())).unwrap_err();
        assert_eq!(e.code(), Code::Unauthenticated);
        assert!(!e.message().contains("abc"));
        let mut r = Request::new(());
        r.metadata_mut()
            .insert("authorization", "Bearer abc".parse().unwrap());
        assert!(g.call(r).is_ok());
        assert!(Gate::new(None).call(Request::new(())).is_ok());
    }

    #[test]
    fn stream_errors_name_their_frame() {
        let e = in_stream(Status::invalid_argument("bad stamp"), 3, "t-42");
        assert_eq!(e.code(), Code::InvalidArgument);
        assert_eq!(
            e.message(),
            "frame 3 of this stream (the first is 1, request_id \"t-42\"): bad stamp"
        );
        // No id, or one refused for its length: not echoed.
        let plain = "frame 7 of this stream (the first is 1): bad stamp";
        let e = in_stream(Status::invalid_argument("bad stamp"), 7, "");
        assert_eq!(e.message(), plain);
        let e = in_stream(
            Status::invalid_argument("bad stamp"),
            7,
            &"x".repeat(100_000),
        );
        assert_eq!(e.message(), plain);
    }

    #[test]
    fn request_ids() {
        let mut m = MetadataMap::new();
        assert_eq!(request_id("given", &m).unwrap(), "given");
        assert_eq!(request_id("", &m).unwrap().len(), 16);
        m.insert("x-request-id", "from-meta".parse().unwrap());
        assert_eq!(request_id("", &m).unwrap(), "from-meta");
        assert!(request_id("has space", &m).is_err());
        assert!(request_id(&"x".repeat(200), &m).is_err());
    }

    fn answer(x: f64, mode: proto::Mode) -> proto::LocalizeResponse {
        proto::LocalizeResponse {
            status: proto::Status::Localized as i32,
            pose: Some(proto::Pose {
                translation: Some(proto::Vector3 { x, y: 0.0, z: 0.0 }),
                rotation: Some(proto::Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                    w: 1.0,
                }),
            }),
            map_id: "m".into(),
            mode: mode as i32,
            ..Default::default()
        }
    }

    #[test]
    fn a_track_is_confirmed_by_agreement_and_anchored_by_map_fixes() {
        let odometry = |odometry| Followup {
            odometry,
            ..Followup::default()
        };
        // A first global fix is not tracked until a second agrees.
        let first = Track::after(None, &answer(0.0, proto::Mode::Global), odometry(false)).unwrap();
        assert!(!first.confirmed);
        assert!(first.next("", None).region.is_none());
        let far = Track::after(
            Some(&first),
            &answer(9.0, proto::Mode::Global),
            odometry(false),
        );
        assert!(
            !far.unwrap().confirmed,
            "a disagreeing fix confirms nothing"
        );
        let t = Track::after(
            Some(&first),
            &answer(0.3, proto::Mode::Global),
            odometry(false),
        )
        .unwrap();
        assert!(t.confirmed);
        let next = t.next("m", None);
        assert!(next.stream && next.region.is_some() && !next.map_first);
        assert!(
            t.next("other", None).region.is_none(),
            "another map is not tracked"
        );
        // Odometry keeps the chain's anchor time; a map fix renews it.
        let kept = Track::after(
            Some(&t),
            &answer(0.35, proto::Mode::Tracking),
            odometry(true),
        );
        let kept = kept.unwrap();
        assert!(kept.confirmed);
        assert_eq!(
            kept.anchored_at, t.anchored_at,
            "odometry does not re-anchor"
        );
        // An old anchor tries the map first, at most once per REANCHOR_AFTER_S.
        let mut aging = Track::after(
            Some(&t),
            &answer(0.35, proto::Mode::Tracking),
            odometry(true),
        )
        .unwrap();
        aging.anchored_at.at -= Duration::from_secs_f64(REANCHOR_AFTER_S + 0.1);
        assert!(aging.next("m", None).map_first);
        aging.map_tried_at = Some(Moment::now(None));
        assert!(!aging.next("m", None).map_first, "the map was just tried");
        let hop = Track::after(
            Some(&aging),
            &answer(0.36, proto::Mode::Tracking),
            odometry(true),
        )
        .unwrap();
        assert_eq!(hop.map_tried_at, aging.map_tried_at, "odometry keeps it");
        aging.map_tried_at = aging.map_tried_at.map(|t| Moment {
            at: t.at - Duration::from_secs_f64(REANCHOR_AFTER_S + 0.1),
            ..t
        });
        assert!(aging.next("m", None).map_first, "and tries it again later");
        let renewed = Track::after(
            Some(&kept),
            &answer(0.4, proto::Mode::Tracking),
            odometry(false),
        );
        let renewed = renewed.unwrap();
        assert!(renewed.anchored_at.at > t.anchored_at.at);
        assert!(renewed.map_tried_at.is_none(), "a map fix starts afresh");
        // A fix turned round (a symmetric room) does not confirm a track, even in the same place.
        let mut turned = answer(0.3, proto::Mode::Global);
        turned.pose.as_mut().unwrap().rotation = Some(proto::Quaternion {
            w: 0.0,
            x: 0.0,
            y: 1.0,
            z: 0.0,
        });
        assert!(
            !Track::after(Some(&first), &turned, odometry(false))
                .unwrap()
                .confirmed
        );
        // After a gap a map fix must be confirmed again, odometry continues.
        let mut stale = Track::after(
            Some(&kept),
            &answer(0.5, proto::Mode::Tracking),
            odometry(false),
        );
        let stale = stale.as_mut().unwrap();
        stale.at.at -= Duration::from_secs_f64(RECONFIRM_AFTER_S + 0.5);
        let late = Track::after(
            Some(stale),
            &answer(1.5, proto::Mode::Tracking),
            odometry(false),
        );
        assert!(!late.unwrap().confirmed);
        let late = Track::after(
            Some(stale),
            &answer(1.5, proto::Mode::Tracking),
            odometry(true),
        );
        assert!(late.unwrap().confirmed);
        // A frame that is not LOCALIZED leaves the state as it was.
        let mut refused = answer(5.0, proto::Mode::Global);
        refused.status = proto::Status::NotLocalized as i32;
        assert!(Track::after(Some(&kept), &refused, odometry(false)).is_none());
    }

    #[test]
    fn a_stream_with_capture_stamps_judges_motion_by_them() {
        let at = |stamp: f64, odometry: bool| Followup {
            odometry,
            stamp_s: Some(stamp),
            ..Followup::default()
        };
        let first = Track::after(None, &answer(0.0, proto::Mode::Global), at(10.0, false)).unwrap();
        let mut t = Track::after(
            Some(&first),
            &answer(0.2, proto::Mode::Global),
            at(10.1, false),
        )
        .unwrap();
        assert!(t.confirmed);
        // The frames reached the server long apart (a slow server, a burst), the camera's clock
        // says 0.1 s: no re-anchoring yet, and the region is what 0.1 s of motion allows.
        t.at.at -= Duration::from_secs(2);
        t.anchored_at.at -= Duration::from_secs(2);
        let soon = t.next("m", Some(10.2));
        assert!(!soon.map_first);
        let region = soon.region.expect("tracked");
        assert!(!region.contains(&Vector3::new(1.6, 0.0, 0.0)));
        // A replay five times faster than its recording: the server's clock says 0.1 s, the
        // camera's 0.6 s: the map is tried again, and the region allows 0.5 s of motion.
        let mut fast = t.clone();
        fast.at.at = Instant::now();
        fast.anchored_at.at = Instant::now();
        let later = fast.next("m", Some(10.7));
        assert!(later.map_first);
        assert!(later.region.unwrap().contains(&Vector3::new(1.6, 0.0, 0.0)));
        // Stamps that stopped advancing (a client repeating one) count a tenth of the server's
        // clock: the track is still checked against the map.
        let mut frozen = fast.clone();
        frozen.anchored_at = Moment {
            at: Instant::now() - Duration::from_secs(6),
            stamp_s: Some(10.1),
        };
        assert!(frozen.next("m", Some(10.1)).map_first);
        // Without a stamp on either side, the server's clock decides, as before.
        assert!(t.next("m", None).map_first);
        assert!(!fast.next("m", None).map_first);
        // A later fix that came 2 s after the last by the server's clock but 0.2 s by the
        // camera's is recent: it keeps the track's confirmation.
        let fix = Track::after(Some(&t), &answer(0.3, proto::Mode::Global), at(10.3, false));
        assert!(fix.unwrap().confirmed);
        let late = Track::after(Some(&t), &answer(0.3, proto::Mode::Global), at(12.3, false));
        assert!(
            !late.unwrap().confirmed,
            "2.2 s by the camera's clock is a gap"
        );
        // Two confident answers elsewhere that reached the server 3 s apart but were taken 0.2 s
        // apart agree: they move the track (by the server's clock they would not).
        let mut sure = Track::after(
            Some(&t),
            &proto::LocalizeResponse {
                inliers: 120,
                confidence: 0.8,
                ..answer(0.3, proto::Mode::Tracking)
            },
            at(10.3, false),
        )
        .unwrap();
        let mut unstamped = sure.clone();
        let far = Isometry3::translation(-6.0, 0.0, 0.0);
        let nearby = Isometry3::translation(-5.9, 0.0, 0.0);
        assert!(sure.challenged(&far, 0.95, Some(20.0)).is_none());
        sure.challenger.as_mut().unwrap().at.at -= Duration::from_secs(3);
        let moved = sure.challenged(&nearby, 0.97, Some(20.2));
        assert_eq!(moved.expect("two agree").position_m.x, -5.9);
        assert!(unstamped.challenged(&far, 0.95, None).is_none());
        unstamped.challenger.as_mut().unwrap().at.at -= Duration::from_secs(3);
        assert!(unstamped.challenged(&nearby, 0.97, None).is_none());
    }

    #[test]
    fn stamps_in_other_units_are_refused_by_name() {
        assert_eq!(decode::stamp(None).unwrap(), None);
        assert_eq!(decode::stamp(Some(0.0)).unwrap(), Some(0.0));
        assert_eq!(
            decode::stamp(Some(1_767_225_600.25)).unwrap(),
            Some(1_767_225_600.25)
        );
        for (bad, named) in [
            (1_767_225_600_250.0, "milliseconds"),
            (1.767_225_6e18, "nanoseconds"),
            (-1.0, "finite number of seconds"),
            (f64::NAN, "finite number of seconds"),
        ] {
            let e = decode::stamp(Some(bad)).unwrap_err();
            assert_eq!(e.code(), Code::InvalidArgument);
            assert!(e.message().contains(named), "{bad}: {}", e.message());
        }
    }

    #[test]
    fn weak_fixes_are_followed_but_answered_only_once_the_map_agrees_again() {
        let fix = |x: f64, inliers: u32, mode: proto::Mode| proto::LocalizeResponse {
            inliers,
            confidence: 0.9,
            ..answer(x, mode)
        };
        let map_fix = Followup::default();
        let hop = || Followup {
            odometry: true,
            ..Followup::default()
        };
        // A strong first fix answers at once.
        let strong = Track::after(None, &fix(0.0, 120, proto::Mode::Global), map_fix).unwrap();
        assert!(strong.established);
        // Two weak fixes that agree (a look-alike room agrees with itself) are tracked, not answered.
        let first = Track::after(
            None,
            &fix(0.0, 18, proto::Mode::Global),
            Followup::default(),
        )
        .unwrap();
        let second = Track::after(
            Some(&first),
            &fix(0.2, 14, proto::Mode::Global),
            Followup::default(),
        )
        .unwrap();
        assert!(second.confirmed && !second.established);
        let carried =
            Track::after(Some(&second), &fix(0.3, 150, proto::Mode::Tracking), hop()).unwrap();
        assert!(
            carried.confirmed && !carried.established,
            "odometry adds no map evidence"
        );
        let mut r = fix(0.3, 150, proto::Mode::Tracking);
        provisional(&mut r, &carried);
        assert_eq!(r.status, proto::Status::NotLocalized as i32);
        assert_eq!(r.cause, proto::NotLocalizedCause::Unverified as i32);
        assert!(
            r.pose.is_none() && r.reason.starts_with("re-acquiring:"),
            "{r:?}"
        );
        // A later map fix that agrees with the confirmed track carried there establishes it.
        let anchored = Track::after(
            Some(&carried),
            &fix(0.35, 20, proto::Mode::Tracking),
            Followup::default(),
        )
        .unwrap();
        assert!(anchored.established);
        // ... but only one that follows the camera's motion. A look-alike's weak fixes lie near
        // enough for the tracking region, not for the motion: 0.3 m from where the frame's own
        // odometry put it, or (when the keyframe did not register the frame) 0.35 m from where
        // the track was a moment ago, they establish nothing.
        let gap = |m: f64| Followup {
            track_gap: Some((m, 1.0)),
            ..Followup::default()
        };
        let slid = Track::after(
            Some(&carried),
            &fix(0.35, 20, proto::Mode::Tracking),
            gap(0.3),
        )
        .unwrap();
        assert!(slid.confirmed && !slid.established);
        let jumped = Track::after(
            Some(&carried),
            &fix(0.65, 20, proto::Mode::Tracking),
            Followup::default(),
        )
        .unwrap();
        assert!(jumped.confirmed && !jumped.established);
        let follows = Track::after(
            Some(&carried),
            &fix(0.35, 20, proto::Mode::Tracking),
            gap(0.03),
        )
        .unwrap();
        assert!(follows.established);
        // A weak fix the map's views preferred to the track's own pose (the track had slipped
        // 0.3 m) takes an established track over; a track not yet established stays so.
        let slipped_from = |track: &Track| {
            let f = Followup {
                track_slipped: true,
                ..gap(0.3)
            };
            Track::after(Some(track), &fix(0.65, 20, proto::Mode::Tracking), f).unwrap()
        };
        let taken = slipped_from(&anchored);
        assert!(taken.confirmed && taken.established);
        assert_eq!(taken.position_m.x, 0.65);
        let still = slipped_from(&carried);
        assert!(!still.established);
        // The same fix without the views' word is one that does not follow the motion.
        let unrefereed = Track::after(
            Some(&anchored),
            &fix(0.65, 20, proto::Mode::Tracking),
            gap(0.3),
        )
        .unwrap();
        assert!(!unrefereed.established);
        let on =
            Track::after(Some(&anchored), &fix(0.4, 90, proto::Mode::Tracking), hop()).unwrap();
        assert!(on.established, "odometry keeps it");
        // Outside the mapped area the track follows odometry's pose without answering ...
        let mut outside = fix(2.0, 80, proto::Mode::Tracking);
        outside.status = proto::Status::NotLocalized as i32;
        outside.pose = None;
        let dead = Followup {
            odometry: true,
            dead_reckoned: Some(Isometry3::translation(2.0, 0.0, 0.0)),
            ..Followup::default()
        };
        let followed = Track::after(Some(&on), &outside, dead).unwrap();
        assert_eq!(followed.position_m.x, 2.0);
        assert!(followed.established && followed.anchored_at == on.anchored_at);
        // ... and any other refusal leaves the last fix.
        assert!(Track::after(Some(&followed), &outside, Followup::default()).is_none());
    }

    #[test]
    fn two_confident_agreeing_answers_outside_a_track_move_it() {
        let fix = |x: f64| proto::LocalizeResponse {
            confidence: 0.8,
            inliers: 120,
            ..answer(x, proto::Mode::Global)
        };
        let first = Track::after(None, &fix(0.0), Followup::default()).unwrap();
        let mut t = Track::after(Some(&first), &fix(0.3), Followup::default()).unwrap();
        assert!(t.confirmed && t.established);
        let far = |x: f64| Isometry3::translation(x, 0.0, 0.0);
        assert!(t.challenged(&far(3.0), 0.7, None).is_none());
        assert!(
            t.challenger.is_none(),
            "an answer less confident than the track's fix is a look-alike"
        );
        assert!(
            t.challenged(&far(3.0), 0.95, None).is_none(),
            "one answer is not enough"
        );
        // The track's odometry answers in between keep the challenger.
        t = Track::after(
            Some(&t),
            &proto::LocalizeResponse {
                confidence: 0.8,
                ..answer(0.35, proto::Mode::Tracking)
            },
            Followup {
                odometry: true,
                ..Followup::default()
            },
        )
        .unwrap();
        assert!(t.challenger.is_some());
        assert!(
            t.challenged(&far(-6.0), 0.95, None).is_none(),
            "two challengers that disagree move nothing"
        );
        let moved = t.challenged(&far(-5.9), 0.99, None).expect("two agree");
        assert!(moved.confirmed && moved.keyframe.is_none());
        assert_eq!(moved.position_m.x, -5.9);
        assert_eq!(moved.confidence, 0.95);
        assert!(moved
            .next("m", None)
            .region
            .unwrap()
            .contains(&Vector3::new(-5.8, 0.0, 0.0)));
        // A track not established yet (one weak fix) is replaced by one more confident answer
        // elsewhere, as a first fix: unconfirmed, not answered until it is established in turn.
        let mut weak = Track::after(
            None,
            &proto::LocalizeResponse {
                confidence: 0.8,
                inliers: 18,
                ..answer(0.0, proto::Mode::Global)
            },
            Followup::default(),
        )
        .unwrap();
        assert!(!weak.established);
        assert!(
            weak.challenged(&far(-6.0), 0.7, None).is_none(),
            "less confident"
        );
        let restarted = weak
            .challenged(&far(-6.0), 0.95, None)
            .expect("one is enough");
        assert!(!restarted.confirmed && !restarted.established);
        assert_eq!(restarted.position_m.x, -6.0);
        // The frame whose answer moved the track is not answered with the old track's pose.
        let mut r = proto::LocalizeResponse {
            status: proto::Status::Localized as i32,
            covariance: vec![0.01; 36],
            ..answer(0.4, proto::Mode::Tracking)
        };
        superseded(&mut r, true);
        assert_eq!(r.status, proto::Status::NotLocalized as i32);
        assert_eq!(r.cause, proto::NotLocalizedCause::LookAlike as i32);
        assert!(r.pose.is_none() && r.covariance.is_empty());
    }

    #[test]
    fn frames_the_map_has_not_matched_for_a_second_say_outside_the_mapped_area() {
        use proto::NotLocalizedCause as C;
        let refused = |cause: C, confidence: f64, reason: &str| proto::LocalizeResponse {
            status: proto::Status::NotLocalized as i32,
            cause: cause as i32,
            confidence,
            reason: reason.into(),
            min_confidence: 0.7,
            ..Default::default()
        };
        let no_match = || {
            refused(
                C::NoMatch,
                0.0,
                "registration: no candidate gave a valid registration",
            )
        };
        let unlikely = || {
            refused(
                C::Unverified,
                0.03,
                "verification: confidence 0.03 below the threshold",
            )
        };
        let unsure = || refused(C::Unverified, 0.5, "verification: confidence 0.50 below");
        let blocked = || {
            refused(
                C::BadInput,
                0.0,
                "input: only 3 keypoints lie on valid depth",
            )
        };
        let localized = proto::LocalizeResponse {
            status: proto::Status::Localized as i32,
            confidence: 0.0,
            ..Default::default()
        };
        // Misses: no registration, an unlikely pose, a camera already dead-reckoned outside.
        for r in [
            no_match(),
            unlikely(),
            refused(C::OutsideMap, 0.0, "outside the mapped area: odometry"),
        ] {
            assert_eq!(Verdict::of(&r), Verdict::Missed, "{r:?}");
        }
        // Unsure: a pose the map doubts, a look-alike, a stream re-acquiring on a weak fix, and a
        // refusal at the map's own threshold when that is below MISS_CONFIDENCE (a place that
        // verified, held loosely).
        let loose = proto::LocalizeResponse {
            min_confidence: 0.1,
            ..refused(C::Unverified, 0.15, "verification: the place verifies")
        };
        for r in [
            unsure(),
            refused(C::LookAlike, 0.9, "verification: a pose turned"),
            refused(C::Unverified, 0.0, "re-acquiring: the stream's map fix"),
            loose,
        ] {
            assert_eq!(Verdict::of(&r), Verdict::Unsure, "{r:?}");
        }
        // Neither: a LOCALIZED answer, a starved frame (the camera may be blocked).
        assert_eq!(Verdict::of(&localized), Verdict::Other);
        assert_eq!(Verdict::of(&blocked()), Verdict::Other);

        let map = ("m", 1);
        // Stamped frames at 10 Hz: misses say "outside" from the run's first second on.
        let mut misses = Misses::default();
        for k in 0..10 {
            let stamp = 5.0 + 0.1 * k as f64;
            assert_eq!(
                misses.after(&unlikely(), map, Some(stamp)),
                None,
                "frame {k}"
            );
        }
        let run = misses
            .after(&no_match(), map, Some(6.0))
            .expect("a second of misses");
        assert!((run.seconds - 1.0).abs() < 1e-9 && run.missed == 11 && run.frames == 11);
        let mut r = no_match();
        outside_map(&mut r, run);
        assert_eq!(r.cause, C::OutsideMap as i32);
        assert!(r.reason.starts_with(OUTSIDE_MAP_PREFIX), "{}", r.reason);
        assert!(
            r.reason
                .contains("for 1.0 s (the map matched none of the last 11 frames")
                && r.reason.contains("no candidate gave"),
            "{}",
            r.reason
        );
        // A dead-reckoned answer keeps its own reason.
        let mut own = refused(C::OutsideMap, 0.0, "outside the mapped area: odometry");
        outside_map(&mut own, run);
        assert_eq!(own.reason, "outside the mapped area: odometry");
        // Unsure frames are not relabelled and do not end the run; the next miss still says so.
        assert_eq!(misses.after(&unsure(), map, Some(6.1)), None);
        let run = misses
            .after(&no_match(), map, Some(6.2))
            .expect("the run goes on");
        assert!(run.missed == 12 && run.frames == 13);
        let mut r = unlikely();
        outside_map(&mut r, run);
        assert!(
            r.reason.contains("none of 12 of the last 13 frames"),
            "{}",
            r.reason
        );
        // A blocked camera's frame ends the run: misses for less than a second after it say
        // nothing of the map, a second of them does again; a LOCALIZED answer ends it too.
        assert_eq!(misses.after(&blocked(), map, Some(6.3)), None);
        for k in 0..9 {
            let stamp = 6.4 + 0.1 * k as f64;
            assert_eq!(misses.after(&no_match(), map, Some(stamp)), None);
        }
        assert!(misses.after(&no_match(), map, Some(7.4)).is_some());
        assert_eq!(misses.after(&localized, map, Some(7.5)), None);
        assert_eq!(misses.after(&no_match(), map, Some(7.6)), None);
        // Another map, or a new version of this one, starts anew; so does a long gap.
        let mut other = Misses::default();
        for (k, m) in [map, map, map, ("m", 2), ("m", 2)].into_iter().enumerate() {
            assert_eq!(
                other.after(&no_match(), m, Some(0.4 * k as f64)),
                None,
                "{k}"
            );
        }
        assert_eq!(other.after(&no_match(), ("n", 2), Some(2.0)), None);
        let mut gap = Misses::default();
        assert_eq!(gap.after(&no_match(), map, Some(0.0)), None);
        assert_eq!(gap.after(&no_match(), map, Some(0.1)), None);
        assert_eq!(gap.after(&no_match(), map, Some(30.0)), None, "after 30 s");
        // An unsure frame starts no run: its time does not count towards the second.
        let mut sparse = Misses::default();
        assert_eq!(sparse.after(&unsure(), map, Some(0.0)), None);
        for stamp in [0.5, 0.8, 1.2] {
            assert_eq!(sparse.after(&no_match(), map, Some(stamp)), None, "{stamp}");
        }
        assert!(sparse.after(&no_match(), map, Some(1.5)).is_some());
        // Without stamps the server's clock measures the run (a second of it is a second here).
        let mut unstamped = Misses::default();
        for _ in 0..3 {
            assert_eq!(unstamped.after(&no_match(), map, None), None);
        }
    }
}
