//! The `pntr.v1.Localizer` implementation: resolve the map, decode and check the frame, queue it for
//! a worker, wait for the answer within the client's deadline, and account for it in metrics.
//!
//! The async side never runs the pipeline: it only decodes, validates and waits, so a handful of
//! runtime threads serve any number of connections while the worker pool bounds the CPU work.

use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use pntr_pipeline::prior::LocalizeOptions;
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
use crate::track::{Followup, StreamMemory, Tracking};
use crate::visual::Shown;
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

    /// Hand an answer to the live view's thread, when someone watches; drawing never holds up
    /// the answer.
    fn show(&self, shown: Option<Shown>) {
        if let (Some(live), Some(shown)) = (self.state.live(), shown) {
            live.show(shown);
        }
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
    ) -> Result<(proto::LocalizeResponse, Followup, Option<Shown>), Status> {
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
            Ok((r, ..)) => {
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
    ) -> Result<(proto::LocalizeResponse, Followup, Option<Shown>), Status> {
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
        // The answer's position uncertainty (LOCALIZED or carried by odometry), for the stream.
        let sigma_m = loc
            .covariance
            .as_deref()
            .map(pntr_pipeline::pipeline::position_sigma_m);
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
            // A stream's memory says (crate::track); unary answers have no track.
            track_state: proto::TrackState::Unspecified as i32,
        };
        // What the live view shows of the answer, once it is final (a stream's after its state
        // has taken it: `StreamMemory::after` may withhold the pose).
        let shown = watched.map(|(_, rgb, k)| Shown {
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
            track_state: "",
        });
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
            contradicted: loc.contradicted.clone(),
            track_gap: loc.track_gap,
            track_slipped: loc.track_slipped,
            stamp_s: None,
            sigma_m,
            robot_odometry: None,
        };
        release(lm);
        Ok((response, followup, shown))
    }
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
            .map(|(mut r, f, shown)| {
                self.show(shown);
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
                // The stream's memory of where its camera is (crate::track).
                let mut memory = StreamMemory::default();
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
                    let stamp_s = match decode::stamp(msg.stamp_s) {
                        Ok(s) => s,
                        Err(e) => {
                            count("ERROR", e.code(), &map.id);
                            let _ = tx.send(Err(in_stream(e, n, &msg.request_id))).await;
                            break;
                        }
                    };
                    let relocalize = msg.relocalize;
                    let convention = this.state.loaded().and_then(|e| {
                        decode::frame_convention(msg.frame_convention, e.frame_convention)
                    });
                    let tracking = match convention
                        .and_then(|c| memory.before(&map, &msg, c, stamp_s))
                    {
                        Ok(t) => t,
                        Err(e) => {
                            count("ERROR", e.code(), &map.id);
                            let _ = tx.send(Err(in_stream(e, n, &msg.request_id))).await;
                            break;
                        }
                    };
                    let sent_id = msg.request_id.clone();
                    let map_key = (map.id.clone(), map.serial);
                    let result =
                        match id {
                            Ok(id) => this.one(msg, Some(map), id.clone(), deadline, tracking).await.map(
                                |(mut r, f, shown)| {
                                    r.request_id = id;
                                    (r, f, shown)
                                },
                            ),
                            Err(e) => {
                                count("ERROR", e.code(), &map.id);
                                Err(e)
                            }
                        };
                    let result = result.map(|(mut r, f, shown)| {
                        memory.after(&mut r, f, stamp_s, relocalize, (&map_key.0, map_key.1), n);
                        count_answer(&r, &r.map_id);
                        this.show(shown.map(|s| s.as_answered(&r)));
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
}
