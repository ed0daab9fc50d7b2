//! Settings of `pntr-server`: command line, environment (`PNTR_*`), a TOML or JSON file, defaults.
//!
//! Precedence, highest first: a command-line flag, its `PNTR_*` environment variable, the config file
//! (`--config` / `PNTR_CONFIG`), the built-in default. Everything is checked once, at start, before
//! anything is bound or loaded, and each error names the setting and where its value came from, so a
//! deployment mistake fails fast with a message instead of surfacing as a confusing runtime error.
//! Relative paths in a config file are relative to the file's folder.
//!
//! The bearer token is never printed: `Settings`' `Debug` redacts it, and `--token-file` /
//! `PNTR_TOKEN` keep it out of the process list.

use std::net::{SocketAddr, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

/// A setting that cannot work.
#[derive(Debug, thiserror::Error)]
#[error("configuration: {0}")]
pub struct ConfigError(pub String);

fn bad<T>(m: impl Into<String>) -> Result<T, ConfigError> {
    Err(ConfigError(m.into()))
}

/// Default gRPC address.
pub const DEFAULT_ADDR: &str = "127.0.0.1:50051";
/// Default address of the Prometheus `/metrics` endpoint.
pub const DEFAULT_METRICS_ADDR: &str = "127.0.0.1:9464";
/// Default maximum size of one gRPC message (a 4096 x 4096 raw RGB frame with float depth is 112 MiB,
/// a 640 x 480 one 2 MiB).
pub const DEFAULT_MAX_MESSAGE_BYTES: usize = 16 << 20;
/// Default most concurrent RPCs per client connection (HTTP/2 SETTINGS_MAX_CONCURRENT_STREAMS). A robot
/// needs one; a load balancer multiplexing many robots needs more. The request queue bounds the work
/// either way; this bounds what one connection can hold open.
pub const DEFAULT_MAX_STREAMS_PER_CONNECTION: u32 = 64;
/// Default most LocalizeStreams open at once on one server, all connections together. Each holds its
/// tracking state (about 1 MB at 640x480: [`crate::service`]'s `Track`) until it ends, so this bounds
/// the memory streams take; a robot needs one, and a 2-core server answers about 9 robots at 5 Hz.
pub const DEFAULT_MAX_STREAMS: usize = 1024;
/// Default largest accepted image side.
pub const DEFAULT_MAX_IMAGE_SIDE: u32 = 4096;
/// Default time in-flight requests get to finish after SIGTERM/SIGINT.
pub const DEFAULT_DRAIN_TIMEOUT_S: f64 = 30.0;
/// Default interval of the HTTP/2 PINGs the server sends on every connection. A robot that drops off
/// the network without closing its connection leaves a half-open TCP connection behind; the ping that
/// goes unanswered is how the server notices and frees it.
pub const DEFAULT_KEEPALIVE_INTERVAL_S: f64 = 30.0;
/// Default time a PING may go unanswered before the server closes the connection.
pub const DEFAULT_KEEPALIVE_TIMEOUT_S: f64 = 20.0;

/// Command-line arguments (each also read from its `PNTR_*` environment variable).
#[derive(clap::Parser, Debug, Default, Clone)]
#[command(
    name = "pntr-server",
    version,
    about = "The pntr gRPC localization service (pntr.v1.Localizer)"
)]
pub struct Args {
    /// A map file from `pntr build-db`; repeat (or separate with commas) to serve several maps. With no
    /// map named here, in PNTR_DB or in a config file, the embedded default is served: the demo
    /// synthetic scene and its map, generated once and cached in $PNTR_DEMO_DIR (default out/demo).
    #[arg(long = "db", env = "PNTR_DB", value_delimiter = ',')]
    pub db: Vec<PathBuf>,
    /// gRPC address, HOST:PORT (port 0 = any free port; the bound one is printed) [default: 127.0.0.1:50051].
    #[arg(long, env = "PNTR_ADDR")]
    pub addr: Option<String>,
    /// Address of the Prometheus /metrics endpoint, HOST:PORT (printed at start) [default:
    /// 127.0.0.1:9464; with --addr on port 0, port 0 of that host].
    #[arg(long, env = "PNTR_METRICS_ADDR")]
    pub metrics_addr: Option<String>,
    /// A TOML (or .json) file with any of these settings (snake_case keys, e.g. `max_message_bytes`).
    #[arg(long, env = "PNTR_CONFIG")]
    pub config: Option<PathBuf>,
    /// Folder of the ONNX models [default: models].
    #[arg(long, env = "PNTR_MODELS")]
    pub models: Option<PathBuf>,
    /// Worker threads running the pipeline, each with its own model sessions [default: CPU count, at most 8].
    #[arg(long, env = "PNTR_WORKERS")]
    pub workers: Option<usize>,
    /// Requests that may wait for a worker; beyond that, RESOURCE_EXHAUSTED [default: 4 x workers].
    #[arg(long, env = "PNTR_QUEUE")]
    pub queue: Option<usize>,
    /// Largest gRPC message accepted or sent, bytes [default: 16 MiB].
    #[arg(long, env = "PNTR_MAX_MESSAGE_BYTES")]
    pub max_message_bytes: Option<usize>,
    /// Most concurrent RPCs (HTTP/2 streams) one client connection may have open; further calls wait
    /// in the client until one ends [default: 64].
    #[arg(long, env = "PNTR_MAX_STREAMS_PER_CONNECTION")]
    pub max_streams_per_connection: Option<u32>,
    /// Most LocalizeStreams open at once, all connections together; one more is refused with
    /// RESOURCE_EXHAUSTED. Each holds its tracking state (about 1 MB) until it ends [default: 1024].
    #[arg(long, env = "PNTR_MAX_STREAMS")]
    pub max_streams: Option<usize>,
    /// Largest accepted image width [default: 4096].
    #[arg(long, env = "PNTR_MAX_IMAGE_WIDTH")]
    pub max_image_width: Option<u32>,
    /// Largest accepted image height [default: 4096].
    #[arg(long, env = "PNTR_MAX_IMAGE_HEIGHT")]
    pub max_image_height: Option<u32>,
    /// ONNX Runtime intra-op threads per worker [default: 1].
    #[arg(long, env = "PNTR_ORT_THREADS")]
    pub ort_threads: Option<usize>,
    /// Where models run: `cpu` or `cuda[:N]` (needs a build with the `cuda` feature and the GPU build of
    /// ONNX Runtime; falls back to the CPU with a warning) [default: cpu].
    #[arg(long, env = "PNTR_DEVICE")]
    pub device: Option<String>,
    /// Seconds in-flight requests get to finish after SIGTERM/SIGINT [default: 30].
    #[arg(long, env = "PNTR_DRAIN_TIMEOUT_S")]
    pub drain_timeout_s: Option<f64>,
    /// Seconds between the HTTP/2 PINGs sent on every connection to find dead peers; 0 turns them off
    /// [default: 30].
    #[arg(long, env = "PNTR_KEEPALIVE_INTERVAL_S")]
    pub keepalive_interval_s: Option<f64>,
    /// Seconds a PING may go unanswered before the connection is closed [default: 20].
    #[arg(long, env = "PNTR_KEEPALIVE_TIMEOUT_S")]
    pub keepalive_timeout_s: Option<f64>,
    /// Require `authorization: Bearer <TOKEN>` on every RPC but health (prefer PNTR_TOKEN or --token-file:
    /// a flag is visible in the process list).
    #[arg(long, env = "PNTR_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Read the bearer token from this file (surrounding whitespace is ignored).
    #[arg(long, env = "PNTR_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// Turn on map administration (`pntr.v1.MapAdmin`: `pntr maps list|load|replace|unload|extend|reload`) with this
    /// token, which admin calls must send as `authorization: Bearer <TOKEN>` and which must differ
    /// from --token (prefer PNTR_ADMIN_TOKEN or --admin-token-file) [default: off, every admin call
    /// refused].
    #[arg(long, env = "PNTR_ADMIN_TOKEN", hide_env_values = true)]
    pub admin_token: Option<String>,
    /// Read the admin token from this file (surrounding whitespace is ignored).
    #[arg(long, env = "PNTR_ADMIN_TOKEN_FILE")]
    pub admin_token_file: Option<PathBuf>,
    /// TLS certificate chain (PEM); needs --tls-key.
    #[arg(long, env = "PNTR_TLS_CERT")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM); needs --tls-cert.
    #[arg(long, env = "PNTR_TLS_KEY")]
    pub tls_key: Option<PathBuf>,
    /// Confidence calibration file from `pntr calibrate`, for every map [default: each map's own,
    /// fitted by `pntr build-db`, else the one shipped in models/,
    /// embedded in the binary].
    #[arg(long, env = "PNTR_CALIBRATION")]
    pub calibration: Option<PathBuf>,
    /// LOCALIZED threshold on the calibrated confidence, 0..1 (higher: fewer wrong poses, more
    /// NOT_LOCALIZED) [default: the calibration's own, chosen for precision].
    #[arg(long, env = "PNTR_MIN_CONFIDENCE")]
    pub min_confidence: Option<f64>,
    /// Serve every map with this preset instead of the one it was built with. Only a preset that
    /// describes images as the map does is accepted: an `xfeat-mnn` map can be served by
    /// `xfeat-mnn-int8` (queries through the int8 backbone, no rebuild) or `xfeat-mnn-bf16` (the
    /// float backbone in bfloat16 on OpenVINO), and back; a preset of
    /// another extractor or global descriptor is refused at start. A preset with another matcher
    /// (`fast` on an `xfeat-mnn` map) also runs, with a warning that the confidence calibration was
    /// fitted for another preset [default: each map's own].
    #[arg(long, env = "PNTR_PRESET")]
    pub preset: Option<String>,
    /// Arithmetic of the XFeat backbone for maps served with their own preset: `auto` runs it in
    /// bfloat16 on OpenVINO (the map's preset's `-bf16` twin: `xfeat-mnn` -> `xfeat-mnn-bf16`)
    /// where the CPU has AVX-512 BF16 and the models run on the CPU, and in f32 elsewhere (also
    /// when OpenVINO cannot be loaded, with a warning); `f32` always runs the float backbone on
    /// ONNX Runtime. --preset overrides it [default: auto].
    #[arg(long, env = "PNTR_BACKBONE_PRECISION")]
    pub backbone_precision: Option<String>,
    /// Frame convention of answers whose request leaves `frame_convention` unset: `map` (the map's
    /// own world frame and camera axes) or `ros` (REP 103 z-up world, optical camera frame x right,
    /// y down, z forward) [default: map].
    #[arg(long, env = "PNTR_FRAME_CONVENTION")]
    pub frame_convention: Option<String>,
    /// Stream what the server sees and answers (frames, poses, map cameras) live over the Foxglove
    /// WebSocket protocol on this address (e.g. 127.0.0.1:8765; open it in Foxglove with "Open
    /// connection"). No authentication: bind it to a trusted interface [default: off].
    #[arg(long, env = "PNTR_FOXGLOVE")]
    pub foxglove: Option<String>,
}

/// `map` or `ros` (any case).
pub fn parse_frame_convention(s: &str) -> Result<crate::proto::FrameConvention, ConfigError> {
    match s.to_ascii_lowercase().as_str() {
        "map" => Ok(crate::proto::FrameConvention::Map),
        "ros" => Ok(crate::proto::FrameConvention::Ros),
        _ => bad(format!(
            "frame convention `{s}`: use map (the map's own axes) or ros (z-up, optical camera)"
        )),
    }
}

/// Arithmetic of the XFeat backbone for maps served with their own preset (`--backbone-precision`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BackbonePrecision {
    /// bfloat16 on OpenVINO where the CPU has the instructions
    /// ([`pntr_features::openvino::cpu_has_bf16`]) and the models run on the CPU; f32 otherwise.
    Auto,
    /// Always the float backbone (ONNX Runtime): the reference the calibration was fitted with.
    F32,
}

/// `auto` or `f32` (case-insensitive).
pub fn parse_backbone_precision(s: &str) -> Result<BackbonePrecision, ConfigError> {
    match s.to_ascii_lowercase().as_str() {
        "auto" => Ok(BackbonePrecision::Auto),
        "f32" | "float" => Ok(BackbonePrecision::F32),
        _ => bad(format!(
            "backbone precision `{s}`: use auto (bfloat16 where the CPU has AVX-512 BF16, else f32) or f32 (always the float backbone)"
        )),
    }
}

/// `cpu`, `cuda` or `cuda:N`.
pub fn parse_device(s: &str) -> Result<pntr_features::runtime::Device, ConfigError> {
    use pntr_features::runtime::Device;
    match s {
        "cpu" => Ok(Device::Cpu),
        "cuda" => Ok(Device::Cuda(0)),
        _ => match s.strip_prefix("cuda:").and_then(|n| n.parse::<i32>().ok()) {
            Some(n) if n >= 0 => Ok(Device::Cuda(n)),
            _ => bad(format!("device `{s}`: use cpu, cuda or cuda:N")),
        },
    }
}

/// The config file: the same settings as [`Args`], all optional, unknown keys refused.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileSettings {
    db: Option<Vec<PathBuf>>,
    addr: Option<String>,
    metrics_addr: Option<String>,
    models: Option<PathBuf>,
    workers: Option<usize>,
    queue: Option<usize>,
    max_message_bytes: Option<usize>,
    max_streams_per_connection: Option<u32>,
    max_streams: Option<usize>,
    max_image_width: Option<u32>,
    max_image_height: Option<u32>,
    ort_threads: Option<usize>,
    device: Option<String>,
    drain_timeout_s: Option<f64>,
    keepalive_interval_s: Option<f64>,
    keepalive_timeout_s: Option<f64>,
    token: Option<String>,
    token_file: Option<PathBuf>,
    admin_token: Option<String>,
    admin_token_file: Option<PathBuf>,
    tls_cert: Option<PathBuf>,
    tls_key: Option<PathBuf>,
    calibration: Option<PathBuf>,
    min_confidence: Option<f64>,
    preset: Option<String>,
    backbone_precision: Option<String>,
    frame_convention: Option<String>,
    foxglove: Option<String>,
}

impl FileSettings {
    fn read(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .or_else(|e| bad(format!("config file {}: {e}", path.display())))?;
        let json = path.extension().is_some_and(|e| e == "json");
        let mut s: Self = if json {
            serde_json::from_str(&text)
                .or_else(|e| bad(format!("config file {}: {e}", path.display())))?
        } else {
            toml::from_str(&text)
                .or_else(|e| bad(format!("config file {}: {e}", path.display())))?
        };
        // Relative paths are relative to the file, not to wherever the server was started.
        let dir = path.parent().unwrap_or(Path::new("."));
        let fix = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = dir.join(&*p);
            }
        };
        s.db.iter_mut().flatten().for_each(fix);
        [
            &mut s.models,
            &mut s.token_file,
            &mut s.admin_token_file,
            &mut s.tls_cert,
            &mut s.tls_key,
            &mut s.calibration,
        ]
        .into_iter()
        .flatten()
        .for_each(fix);
        Ok(s)
    }
}

/// Validated settings of one server.
#[derive(Clone)]
pub struct Settings {
    /// Map files to serve (at least one).
    pub db: Vec<PathBuf>,
    /// gRPC address.
    pub addr: SocketAddr,
    /// Prometheus endpoint address.
    pub metrics_addr: SocketAddr,
    /// Folder of the ONNX models.
    pub models: PathBuf,
    /// Worker threads.
    pub workers: usize,
    /// Requests that may wait for a worker.
    pub queue: usize,
    /// Largest gRPC message, bytes.
    pub max_message_bytes: usize,
    /// Most concurrent HTTP/2 streams per client connection.
    pub max_streams_per_connection: u32,
    /// Most LocalizeStreams open at once, all connections together.
    pub max_streams: usize,
    /// Largest image width.
    pub max_image_width: u32,
    /// Largest image height.
    pub max_image_height: u32,
    /// ONNX Runtime threads per worker.
    pub ort_threads: usize,
    /// Where models run.
    pub device: pntr_features::runtime::Device,
    /// Time given to in-flight requests at shutdown.
    pub drain_timeout: Duration,
    /// Interval of the server's HTTP/2 keep-alive PINGs (`None`: none are sent).
    pub keepalive_interval: Option<Duration>,
    /// Time a keep-alive PING may go unanswered before the connection is closed.
    pub keepalive_timeout: Duration,
    /// Bearer token required on every RPC but health.
    pub token: Option<String>,
    /// Token of the map administration API (`None`: every admin call is refused).
    pub admin_token: Option<String>,
    /// TLS certificate chain and key (PEM files).
    pub tls: Option<(PathBuf, PathBuf)>,
    /// Confidence calibration file for every map (`None`: each map's own, else the embedded default).
    pub calibration: Option<PathBuf>,
    /// LOCALIZED threshold on the confidence (`None`: the calibration's own).
    pub min_confidence: Option<f64>,
    /// Preset every map is served with (`None`: each map's own, from its header).
    pub preset: Option<String>,
    /// Arithmetic of the backbone for maps served with their own preset.
    pub backbone_precision: BackbonePrecision,
    /// Convention of answers whose request does not choose one (never UNSPECIFIED).
    pub frame_convention: crate::proto::FrameConvention,
    /// Address of the live Foxglove WebSocket view (`None`: off).
    pub foxglove: Option<SocketAddr>,
}

impl std::fmt::Debug for Settings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Settings")
            .field("db", &self.db)
            .field("addr", &self.addr)
            .field("metrics_addr", &self.metrics_addr)
            .field("models", &self.models)
            .field("workers", &self.workers)
            .field("queue", &self.queue)
            .field("max_message_bytes", &self.max_message_bytes)
            .field(
                "max_streams_per_connection",
                &self.max_streams_per_connection,
            )
            .field("max_streams", &self.max_streams)
            .field("max_image_width", &self.max_image_width)
            .field("max_image_height", &self.max_image_height)
            .field("ort_threads", &self.ort_threads)
            .field("device", &self.device)
            .field("drain_timeout", &self.drain_timeout)
            .field("keepalive_interval", &self.keepalive_interval)
            .field("keepalive_timeout", &self.keepalive_timeout)
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .field(
                "admin_token",
                &self.admin_token.as_ref().map(|_| "<redacted>"),
            )
            .field("tls", &self.tls)
            .field("calibration", &self.calibration)
            .field("min_confidence", &self.min_confidence)
            .field("preset", &self.preset)
            .field("backbone_precision", &self.backbone_precision)
            .field("frame_convention", &self.frame_convention)
            .field("foxglove", &self.foxglove)
            .finish()
    }
}

/// A number of seconds from the flags or the file (or `default`), which must lie in `lo..=hi`.
fn seconds(
    name: &str,
    given: Option<f64>,
    default: f64,
    lo: f64,
    hi: f64,
) -> Result<Duration, ConfigError> {
    let s = given.unwrap_or(default);
    if !(s.is_finite() && (lo..=hi).contains(&s)) {
        return bad(format!(
            "{name} must be between {lo} and {hi} seconds, not {s}"
        ));
    }
    Ok(Duration::from_secs_f64(s))
}

/// A token given directly or in a file (not both); `what` names it in errors.
fn token_of(
    what: &str,
    given: Option<String>,
    file: Option<PathBuf>,
) -> Result<Option<String>, ConfigError> {
    match (given, file) {
        (Some(_), Some(_)) => bad(format!("give the {what} or a {what} file, not both")),
        (Some(t), None) => Ok(Some(t)),
        (None, Some(p)) => Ok(Some(
            std::fs::read_to_string(&p)
                .or_else(|e| bad(format!("{what} file {}: {e}", p.display())))?
                .trim()
                .to_string(),
        )),
        (None, None) => Ok(None),
    }
}

fn default_workers() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
        .min(8)
}

impl Settings {
    /// Settings with the defaults for serving `db`, on loopback with ephemeral ports (tests, tools).
    pub fn local(db: Vec<PathBuf>, models: PathBuf) -> Self {
        let any = SocketAddr::from(([127, 0, 0, 1], 0));
        let workers = default_workers();
        Self {
            db,
            addr: any,
            metrics_addr: any,
            models,
            workers,
            queue: 4 * workers,
            max_message_bytes: DEFAULT_MAX_MESSAGE_BYTES,
            max_streams_per_connection: DEFAULT_MAX_STREAMS_PER_CONNECTION,
            max_streams: DEFAULT_MAX_STREAMS,
            max_image_width: DEFAULT_MAX_IMAGE_SIDE,
            max_image_height: DEFAULT_MAX_IMAGE_SIDE,
            ort_threads: 1,
            device: pntr_features::runtime::Device::Cpu,
            drain_timeout: Duration::from_secs_f64(DEFAULT_DRAIN_TIMEOUT_S),
            keepalive_interval: Some(Duration::from_secs_f64(DEFAULT_KEEPALIVE_INTERVAL_S)),
            keepalive_timeout: Duration::from_secs_f64(DEFAULT_KEEPALIVE_TIMEOUT_S),
            token: None,
            admin_token: None,
            tls: None,
            calibration: None,
            min_confidence: None,
            preset: None,
            backbone_precision: BackbonePrecision::Auto,
            frame_convention: crate::proto::FrameConvention::Map,
            foxglove: None,
        }
    }

    /// Merge the command line / environment with the config file and the defaults, then validate.
    pub fn from_args(args: Args) -> Result<Self, ConfigError> {
        let file = match &args.config {
            Some(p) => FileSettings::read(p)?,
            None => FileSettings::default(),
        };
        let db = if args.db.is_empty() {
            file.db.unwrap_or_default()
        } else {
            args.db
        };
        let addr = args
            .addr
            .or(file.addr)
            .unwrap_or_else(|| DEFAULT_ADDR.into());
        // A server on an ephemeral port (tests, several on one machine) gets an ephemeral metrics
        // port too unless one is named: two such servers must not clash on the default 9464.
        let metrics_addr = args.metrics_addr.or(file.metrics_addr).unwrap_or_else(|| {
            match parse_addr("addr", &addr) {
                Ok(a) if a.port() == 0 => SocketAddr::new(a.ip(), 0).to_string(),
                _ => DEFAULT_METRICS_ADDR.into(),
            }
        });
        let workers = args
            .workers
            .or(file.workers)
            .unwrap_or_else(default_workers);
        let token = token_of(
            "token",
            args.token.or(file.token),
            args.token_file.or(file.token_file),
        )?;
        let admin_token = token_of(
            "admin token",
            args.admin_token.or(file.admin_token),
            args.admin_token_file.or(file.admin_token_file),
        )?;
        let tls = match (
            args.tls_cert.or(file.tls_cert),
            args.tls_key.or(file.tls_key),
        ) {
            (Some(c), Some(k)) => Some((c, k)),
            (None, None) => None,
            _ => return bad("TLS needs both --tls-cert and --tls-key"),
        };
        let s = Self {
            db,
            addr: parse_addr("addr", &addr)?,
            metrics_addr: parse_addr("metrics-addr", &metrics_addr)?,
            // Not given: found from the working folder, the executable or the install prefix
            // (`validate` lists where it looked when that fails).
            models: args
                .models
                .or(file.models)
                .or_else(|| pntr_features::models_dir::locate(None).ok())
                .unwrap_or_else(|| PathBuf::from("models")),
            workers,
            queue: args.queue.or(file.queue).unwrap_or(4 * workers),
            max_message_bytes: args
                .max_message_bytes
                .or(file.max_message_bytes)
                .unwrap_or(DEFAULT_MAX_MESSAGE_BYTES),
            max_streams_per_connection: args
                .max_streams_per_connection
                .or(file.max_streams_per_connection)
                .unwrap_or(DEFAULT_MAX_STREAMS_PER_CONNECTION),
            max_streams: args
                .max_streams
                .or(file.max_streams)
                .unwrap_or(DEFAULT_MAX_STREAMS),
            max_image_width: args
                .max_image_width
                .or(file.max_image_width)
                .unwrap_or(DEFAULT_MAX_IMAGE_SIDE),
            max_image_height: args
                .max_image_height
                .or(file.max_image_height)
                .unwrap_or(DEFAULT_MAX_IMAGE_SIDE),
            ort_threads: args.ort_threads.or(file.ort_threads).unwrap_or(1),
            device: parse_device(args.device.or(file.device).as_deref().unwrap_or("cpu"))?,
            drain_timeout: seconds(
                "drain-timeout-s",
                args.drain_timeout_s.or(file.drain_timeout_s),
                DEFAULT_DRAIN_TIMEOUT_S,
                0.0,
                86_400.0,
            )?,
            keepalive_interval: Some(seconds(
                "keepalive-interval-s",
                args.keepalive_interval_s.or(file.keepalive_interval_s),
                DEFAULT_KEEPALIVE_INTERVAL_S,
                0.0,
                3_600.0,
            )?)
            .filter(|d| !d.is_zero()),
            keepalive_timeout: seconds(
                "keepalive-timeout-s",
                args.keepalive_timeout_s.or(file.keepalive_timeout_s),
                DEFAULT_KEEPALIVE_TIMEOUT_S,
                0.1,
                600.0,
            )?,
            token,
            admin_token,
            tls,
            calibration: args.calibration.or(file.calibration),
            min_confidence: args.min_confidence.or(file.min_confidence),
            preset: args.preset.or(file.preset),
            backbone_precision: match args.backbone_precision.or(file.backbone_precision) {
                None => BackbonePrecision::Auto,
                Some(name) => parse_backbone_precision(&name)?,
            },
            frame_convention: match args.frame_convention.or(file.frame_convention) {
                None => crate::proto::FrameConvention::Map,
                Some(name) => parse_frame_convention(&name)?,
            },
            foxglove: match args.foxglove.or(file.foxglove) {
                None => None,
                Some(a) => Some(a.parse().or_else(|e| {
                    bad(format!(
                        "--foxglove `{a}`: {e} (give HOST:PORT, e.g. 127.0.0.1:8765)"
                    ))
                })?),
            },
        };
        s.validate()?;
        Ok(s)
    }

    /// Check every value (also called by [`crate::server::start`] on settings built in code).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.db.is_empty() {
            return bad("no --db given: pass a map file from `pntr build-db` (--db, PNTR_DB or `db` in the config file)");
        }
        for (i, p) in self.db.iter().enumerate() {
            if let Some(what) = pntr_pipeline::mapfile::not_a_regular_file(p) {
                return bad(format!(
                    "--db {}: {}",
                    p.display(),
                    pntr_pipeline::mapfile::not_a_map_file(what)
                ));
            }
            if self.db[..i].contains(p) {
                return bad(format!("--db {} is given twice", p.display()));
            }
        }
        if !self.models.is_dir() {
            let looked: Vec<String> = pntr_features::models_dir::candidates()
                .iter()
                .map(|p| p.display().to_string())
                .collect();
            return bad(format!(
                "models folder {}: no such folder (the ONNX models; see models/README.md); without --models or `models` in the config file, {} and the folders {} are looked at",
                self.models.display(),
                pntr_features::models_dir::ENV,
                looked.join(", ")
            ));
        }
        if !(1..=256).contains(&self.workers) {
            return bad(format!("--workers must be 1 to 256, not {}", self.workers));
        }
        if self.queue > 100_000 {
            return bad(format!(
                "--queue must be at most 100000, not {}",
                self.queue
            ));
        }
        if !(1024..=(1 << 30)).contains(&self.max_message_bytes) {
            return bad(format!(
                "--max-message-bytes must be between 1024 and 1073741824, not {}",
                self.max_message_bytes
            ));
        }
        if !(1..=100_000).contains(&self.max_streams) {
            return bad(format!(
                "--max-streams must be 1 to 100000, not {}",
                self.max_streams
            ));
        }
        if !(1..=10_000).contains(&self.max_streams_per_connection) {
            return bad(format!(
                "--max-streams-per-connection must be 1 to 10000, not {}",
                self.max_streams_per_connection
            ));
        }
        for (name, v) in [
            ("max-image-width", self.max_image_width),
            ("max-image-height", self.max_image_height),
        ] {
            if !(16..=65_536).contains(&v) {
                return bad(format!("--{name} must be between 16 and 65536, not {v}"));
            }
        }
        if !(1..=64).contains(&self.ort_threads) {
            return bad(format!(
                "--ort-threads must be 1 to 64, not {}",
                self.ort_threads
            ));
        }
        if let Some(c) = self.min_confidence {
            if !(0.0..=1.0).contains(&c) {
                return bad(format!("--min-confidence must be between 0 and 1, not {c}"));
            }
        }
        if let Some(p) = &self.calibration {
            pntr_pipeline::calibration::Calibration::load(p)
                .or_else(|e| bad(format!("--calibration: {e}")))?;
        }
        if let Some(name) = &self.preset {
            // Named wrongly or unable to read a map's descriptors: refused before anything is bound.
            let from = "--preset (PNTR_PRESET, `preset` in the config file)";
            let preset = pntr_pipeline::preset::Preset::named(name).or_else(|e| match e {
                pntr_pipeline::PipelineError::Config(m) => bad(format!("{from}: {m}")),
                e => bad(format!("{from}: {e}")),
            })?;
            for path in &self.db {
                // An unreadable header is the map loader's to report, with its own message.
                if let Ok(h) = pntr_pipeline::mapfile::read_header(path) {
                    preset.serves(&h.preset).or_else(|e| {
                        bad(format!(
                            "{from} {name} cannot serve {}: {}",
                            path.display(),
                            match e {
                                pntr_pipeline::PipelineError::Config(m) => m,
                                e => e.to_string(),
                            }
                        ))
                    })?;
                }
            }
        }
        for (what, token) in [
            ("the bearer token", &self.token),
            ("the admin token", &self.admin_token),
        ] {
            if let Some(t) = token {
                // Checked without echoing the value.
                if t.is_empty() {
                    return bad(format!("{what} is empty"));
                }
                if !t.bytes().all(|b| b.is_ascii_graphic()) {
                    return bad(format!("{what} must be printable ASCII without spaces"));
                }
            }
        }
        if self.admin_token.is_some() && self.admin_token == self.token {
            return bad("the admin token must differ from the clients' bearer token (--token): a robot must not be able to change maps");
        }
        if let Some((c, k)) = &self.tls {
            for (name, p) in [("tls-cert", c), ("tls-key", k)] {
                if !p.is_file() {
                    return bad(format!("--{name} {}: no such file", p.display()));
                }
            }
        }
        Ok(())
    }
}

fn parse_addr(name: &str, s: &str) -> Result<SocketAddr, ConfigError> {
    if let Ok(a) = s.parse() {
        return Ok(a);
    }
    // Host names (e.g. localhost:50051) resolve once, at start.
    match s.to_socket_addrs() {
        Ok(mut it) => match it.next() {
            Some(a) => Ok(a),
            None => bad(format!("--{name} {s}: resolves to no address")),
        },
        Err(e) => bad(format!("--{name} {s}: expected HOST:PORT ({e})")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_files() -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("a.pntrmap");
        std::fs::write(&db, b"x").unwrap();
        std::fs::create_dir(dir.path().join("models")).unwrap();
        (dir, db)
    }

    #[test]
    fn devices_parse_and_bad_ones_are_named() {
        use pntr_features::runtime::Device;
        assert_eq!(parse_device("cpu").unwrap(), Device::Cpu);
        assert_eq!(parse_device("cuda").unwrap(), Device::Cuda(0));
        assert_eq!(parse_device("cuda:1").unwrap(), Device::Cuda(1));
        for bad in ["gpu", "cuda:-1", "cuda:x", ""] {
            let e = parse_device(bad).unwrap_err().to_string();
            assert!(e.contains("cpu, cuda or cuda:N"), "{e}");
        }
    }

    #[test]
    fn precedence_and_validation() {
        let (dir, db) = with_files();
        let cfg = dir.path().join("server.toml");
        std::fs::write(
            &cfg,
            "db = [\"a.pntrmap\"]\nmodels = \"models\"\nworkers = 3\nqueue = 2\naddr = \"127.0.0.1:0\"\n",
        )
        .unwrap();
        let args = Args {
            config: Some(cfg.clone()),
            queue: Some(7),
            ..Args::default()
        };
        let s = Settings::from_args(args).unwrap();
        assert_eq!(s.db, vec![db.clone()]);
        assert_eq!(s.workers, 3);
        assert_eq!(s.queue, 7, "the flag wins over the file");
        assert_eq!(s.addr.port(), 0);
        assert_eq!(
            s.metrics_addr.port(),
            0,
            "an ephemeral server gets an ephemeral metrics port, not 9464"
        );
        assert_eq!(s.max_message_bytes, DEFAULT_MAX_MESSAGE_BYTES);
        let s = Settings::from_args(Args {
            config: Some(cfg.clone()),
            metrics_addr: Some("127.0.0.1:9999".into()),
            ..Args::default()
        })
        .unwrap();
        assert_eq!(
            s.metrics_addr.port(),
            9999,
            "a named metrics address is kept"
        );

        std::fs::write(&cfg, "wrkers = 3\n").unwrap();
        let e = Settings::from_args(Args {
            config: Some(cfg.clone()),
            ..Args::default()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("wrkers") && e.contains("server.toml"), "{e}");

        let e = Settings::from_args(Args::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("no --db given"), "{e}");

        let base = Args {
            db: vec![db.clone()],
            models: Some(dir.path().join("models")),
            ..Args::default()
        };
        let e = Settings::from_args(Args {
            workers: Some(0),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("--workers"), "{e}");
        // Keep-alive: on by default, 0 turns it off, nonsense is named.
        let s = Settings::from_args(base.clone()).unwrap();
        assert_eq!(s.keepalive_interval, Some(Duration::from_secs(30)));
        assert_eq!(
            s.max_streams_per_connection,
            DEFAULT_MAX_STREAMS_PER_CONNECTION
        );
        let s = Settings::from_args(Args {
            keepalive_interval_s: Some(0.0),
            ..base.clone()
        })
        .unwrap();
        assert_eq!(s.keepalive_interval, None);
        for (interval, timeout, name) in [
            (Some(-1.0), None, "keepalive-interval-s"),
            (Some(f64::NAN), None, "keepalive-interval-s"),
            (None, Some(0.0), "keepalive-timeout-s"),
        ] {
            let e = Settings::from_args(Args {
                keepalive_interval_s: interval,
                keepalive_timeout_s: timeout,
                ..base.clone()
            })
            .unwrap_err()
            .to_string();
            assert!(e.contains(name), "{e}");
        }
        let e = Settings::from_args(Args {
            max_streams_per_connection: Some(0),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("--max-streams-per-connection"), "{e}");
        assert_eq!(
            Settings::from_args(base.clone()).unwrap().max_streams,
            DEFAULT_MAX_STREAMS
        );
        let e = Settings::from_args(Args {
            max_streams: Some(0),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("--max-streams must be"), "{e}");
        let e = Settings::from_args(Args {
            addr: Some("nonsense".into()),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("--addr nonsense"), "{e}");
        let e = Settings::from_args(Args {
            tls_cert: Some(db.clone()),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("tls-key"), "{e}");
        let s = Settings::from_args(Args {
            token: Some("s3cret-token".into()),
            ..base.clone()
        })
        .unwrap();
        let shown = format!("{s:?}");
        assert!(!shown.contains("s3cret"), "{shown}");
        let s = Settings::from_args(Args {
            token: Some("s3cret-token".into()),
            admin_token: Some("adm1n-token".into()),
            ..base.clone()
        })
        .unwrap();
        assert_eq!(s.admin_token.as_deref(), Some("adm1n-token"));
        assert!(!format!("{s:?}").contains("adm1n"), "{s:?}");
        let e = Settings::from_args(Args {
            token: Some("same-token".into()),
            admin_token: Some("same-token".into()),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("admin token must differ"), "{e}");
        assert!(!e.contains("same-token"), "{e}");
        let e = Settings::from_args(Args {
            admin_token: Some("with space".into()),
            ..base.clone()
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("the admin token must be printable"), "{e}");
        let e = Settings::from_args(Args {
            models: Some(dir.path().join("nope")),
            ..base
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("nope"), "{e}");
    }

    #[test]
    fn json_config() {
        let (dir, db) = with_files();
        let cfg = dir.path().join("server.json");
        std::fs::write(
            &cfg,
            r#"{"db": ["a.pntrmap"], "models": "models", "max_message_bytes": 2048, "drain_timeout_s": 1.5}"#,
        )
        .unwrap();
        let s = Settings::from_args(Args {
            config: Some(cfg),
            ..Args::default()
        })
        .unwrap();
        assert_eq!(s.db, vec![db]);
        assert_eq!(s.max_message_bytes, 2048);
        assert_eq!(s.drain_timeout, Duration::from_millis(1500));
    }
}
