//! The CPU side of the server: the loaded maps and a fixed pool of worker threads fed by a bounded
//! queue.
//!
//! Why a pool of plain threads rather than `spawn_blocking`: localisation is seconds-scale CPU work
//! with ONNX sessions that run one inference at a time per instance. Each worker owns its own feature
//! stage (its own model sessions) and one `Pipeline` per map, so `workers` frames run truly in
//! parallel and never contend on a session lock, and the number of CPU-heavy jobs is fixed however
//! many requests arrive. The queue in front of the workers is a bounded channel: `try_send` fails at
//! once when it is full, which the service turns into RESOURCE_EXHAUSTED, so overload shows up as
//! fast refusals a client can back off from instead of unbounded latency and memory.
//!
//! Deadlines: a job carries its client's deadline. A worker that picks up a job whose deadline has
//! passed, or whose caller has gone (the async side dropped its reply channel on deadline or
//! cancellation), drops it without running the pipeline.

use std::collections::{BTreeSet, HashMap};
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, RwLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use pntr_features::config::FeatureStage;
use pntr_features::runtime::RuntimeOptions;
use pntr_pipeline::map::Map;
use pntr_pipeline::mapfile;
use pntr_pipeline::pipeline::{Localization, Pipeline, Query};
use pntr_pipeline::preset::Preset;
use pntr_pipeline::prior::LocalizeOptions;
use pntr_pipeline::PipelineError;
use pntr_retrieval::onnx_global::OnnxGlobal;
use tokio::sync::oneshot;
use tracing::Span;

use crate::config::{BackbonePrecision, Settings};
use crate::telemetry;

/// One loaded map, with what each worker needs to localize in it. Held by `Arc`: the engine's list
/// holds one, every job in flight another, so a map that is replaced or unloaded is freed when the
/// last job that started on it is done.
pub struct LoadedMap {
    /// The id from the map's header.
    pub id: String,
    /// The map.
    pub map: Arc<Map>,
    /// Distinct (scene, Point) pairs of its images.
    pub points: usize,
    /// The preset it is served with: its header's, or `pntr-server --preset` (same descriptors).
    pub preset: Preset,
    /// Where its preset's extractor network runs ([`pntr_features::Extractor::engine`]).
    pub extractor_engine: &'static str,
    /// The file it was loaded from, as given.
    pub file: PathBuf,
    /// Its version ([`MapVersion`]).
    pub version: MapVersion,
    /// The world frame its poses are in: equal for two loaded maps when a replacement shares the
    /// frame of the map it replaced ([`shares_frame`]), so that a stream's tracking state carries over.
    pub frame: u64,
    /// Unique to this load: a stream's keyframe refers to map images by index, valid only here.
    pub serial: u64,
    /// Size and modification time of the file when it was read (SIGHUP reloads changed files only).
    pub file_stamp: Option<(u64, std::time::SystemTime)>,
    /// The LOCALIZED threshold its answers use: `--min-confidence`, or its calibration's.
    pub min_confidence: f64,
    /// Where its confidence calibration comes from: the map's own, `--calibration`, or shipped.
    pub calibration_source: pntr_pipeline::calibration::CalibrationSource,
    /// True when the map carries its own calibration but changed since it was fitted.
    pub calibration_stale: bool,
    /// One pipeline per worker (each over that worker's own model sessions).
    pipelines: Vec<Pipeline>,
    /// Declared last, so dropped after the map and the pipelines: gives their memory back to the OS.
    _release: ReleaseMemory,
}

/// On drop, returns the C allocator's free memory to the OS. glibc's malloc keeps what a freed map
/// held (hundreds of MB of small blocks, spread over the arenas of the threads that loaded it) for
/// reuse and only trims the top of each heap, so without this every replacement left the process
/// larger by about a map (BENCHMARKS.md, "Live maps"). `malloc_trim` releases the free pages of
/// every arena (glibc 2.8 and later); elsewhere this does nothing.
#[derive(Debug, Default)]
struct ReleaseMemory;

impl Drop for ReleaseMemory {
    fn drop(&mut self) {
        release_free_memory();
    }
}

/// Give the allocator's free pages back to the OS (glibc only; a few milliseconds).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
pub fn release_free_memory() {
    // SAFETY: malloc_trim takes a pad size, touches only the allocator's own free lists, and is
    // thread-safe (it locks each arena in turn).
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Give the allocator's free pages back to the OS (glibc only).
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn release_free_memory() {}

impl std::fmt::Debug for LoadedMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "LoadedMap({} {} from {})",
            self.id,
            self.version.label,
            self.file.display()
        )
    }
}

/// A map's version: its build time and a checksum of its content.
#[derive(Debug, Clone, PartialEq)]
pub struct MapVersion {
    /// [`pntr_pipeline::map::Map::checksum`].
    pub checksum: u64,
    /// When it was built or last extended, seconds since the Unix epoch (`None`: older maps).
    pub built_at_unix_s: Option<f64>,
    /// `20261203T041500Z-3f2a9c1e0b7d4a55`, or `unknown-3f2a9c1e0b7d4a55`.
    pub label: String,
    /// RFC 3339 UTC, or empty.
    pub built_at: String,
}

impl MapVersion {
    /// The version of `map` (its header's build time and its content checksum).
    pub fn of(map: &Map) -> Self {
        let at = map
            .header
            .built_at_unix_s
            .filter(|s| s.is_finite())
            .and_then(|s| time::OffsetDateTime::from_unix_timestamp(s.floor() as i64).ok());
        let compact =
            time::macros::format_description!("[year][month][day]T[hour][minute][second]Z");
        let label = match at.and_then(|t| t.format(&compact).ok()) {
            Some(t) => format!("{t}-{:016x}", map.checksum),
            None => format!("unknown-{:016x}", map.checksum),
        };
        let built_at = at
            .and_then(|t| {
                t.format(&time::format_description::well_known::Rfc3339)
                    .ok()
            })
            .unwrap_or_default();
        Self {
            checksum: map.checksum,
            built_at_unix_s: map.header.built_at_unix_s,
            label,
            built_at,
        }
    }
}

/// Whether map `new` holds its poses in the world frame of `old` (see the proto's
/// `MapChange.same_frame`): the same camera axes and up axis, and among the images both hold under
/// the same id at least 3 (all of `old`'s when it has fewer), whose poses agree within 5 cm and
/// 1 degree at the median.
pub fn shares_frame(old: &Map, new: &Map) -> bool {
    if old.header.camera_axes != new.header.camera_axes || old.header.up_axis != new.header.up_axis
    {
        return false;
    }
    let by_id: HashMap<&str, &pntr_pipeline::map::MapImage> =
        new.images.iter().map(|im| (im.id.as_str(), im)).collect();
    let mut dt = Vec::new();
    let mut dr = Vec::new();
    for a in &old.images {
        if let Some(b) = by_id.get(a.id.as_str()) {
            if old.header.scenes.get(a.scene as usize) != new.header.scenes.get(b.scene as usize) {
                continue;
            }
            let d = a.world_from_camera.inverse() * b.world_from_camera;
            dt.push(d.translation.vector.norm());
            dr.push(d.rotation.angle().to_degrees());
        }
    }
    if dt.len() < 3.min(old.images.len()).max(1) {
        return false;
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    median(&mut dt) <= 0.05 && median(&mut dr) <= 1.0
}

/// A frame waiting for a worker.
pub struct Job {
    /// The map to localize in (held until the job is done).
    pub map: Arc<LoadedMap>,
    /// The decoded frame.
    pub query: Query,
    /// A prior or tracking region to try first.
    pub options: LocalizeOptions,
    /// The client's deadline.
    pub deadline: Option<Instant>,
    /// When it was queued.
    pub enqueued: Instant,
    /// The request's span (the worker's logs carry the request id).
    pub span: Span,
    /// Where the answer goes.
    pub reply: oneshot::Sender<Outcome>,
}

/// What a worker did with a job.
#[derive(Debug)]
pub enum Outcome {
    /// The pipeline ran.
    Done {
        /// Its result.
        result: Result<Box<Localization>, PipelineError>,
        /// Time spent waiting in the queue.
        queued: Duration,
    },
    /// The deadline had passed when a worker picked the job up; the pipeline did not run.
    Expired {
        /// Time spent waiting in the queue.
        queued: Duration,
    },
    /// The pipeline panicked (a bug); the worker survives.
    Panicked {
        /// The panic message.
        message: String,
    },
}

/// Why a map could not be swapped in or out.
#[derive(Debug, thiserror::Error)]
pub enum InstallError {
    /// Loading a map whose id is already loaded.
    #[error("map `{0}` is already loaded: replace it instead")]
    Exists(String),
    /// Replacing or unloading a map that is not loaded.
    #[error("no map `{0}` is loaded")]
    Missing(String),
    /// Replacing a map by a file that holds another map.
    #[error("{file} holds map `{found}`, not `{wanted}`: a map is replaced by a file of the same map id (build it with --map-id {wanted})", file = .file.display())]
    OtherId {
        /// The map to replace.
        wanted: String,
        /// The id in the file.
        found: String,
        /// The file.
        file: PathBuf,
    },
}

/// Why a job was not queued.
#[derive(Debug, PartialEq, Eq)]
pub enum SubmitError {
    /// The queue is full.
    Full,
    /// The pool is shutting down.
    Closed,
}

/// Key of a feature stage: extractor, matcher, keypoints.
type StageKey = (String, String, usize);

/// The maps and the worker pool.
pub struct Engine {
    /// Loaded maps, swapped whole on every change (readers take a snapshot).
    maps: RwLock<Arc<Vec<Arc<LoadedMap>>>>,
    /// Worker threads.
    pub workers: usize,
    /// Queue capacity.
    pub queue: usize,
    /// `--min-confidence`: the LOCALIZED threshold for every map instead of its calibration's.
    min_confidence: Option<f64>,
    /// The convention of answers whose request does not choose one.
    pub frame_convention: crate::proto::FrameConvention,
    runtime: RuntimeOptions,
    models: PathBuf,
    preset_override: Option<String>,
    /// `--backbone-precision`: whether a map served with its own preset runs its bf16 twin.
    backbone_precision: BackbonePrecision,
    /// `--calibration`: one calibration for every map instead of each map's own (or the shipped one).
    calibration: Option<Arc<pntr_pipeline::calibration::Calibration>>,
    /// Each worker's feature stage per preset key, built once and shared by the maps that use it.
    stages: Mutex<HashMap<StageKey, Vec<FeatureStage>>>,
    serial: AtomicU64,
    tx: Mutex<Option<SyncSender<Job>>>,
    queued: Arc<AtomicUsize>,
    busy: Arc<AtomicUsize>,
    threads: Mutex<Vec<JoinHandle<()>>>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let maps = self.maps();
        let ids: Vec<&str> = maps.iter().map(|m| m.id.as_str()).collect();
        write!(
            f,
            "Engine(maps {ids:?}, {} workers, queue {})",
            self.workers, self.queue
        )
    }
}

fn load_map(path: &Path, runtime: &RuntimeOptions) -> Result<Map, PipelineError> {
    let header = mapfile::read_header(path)?;
    let model = header.preset.global_model.clone();
    mapfile::load(path, |dim| {
        let p = model.ok_or_else(|| {
            pntr_retrieval::RetrievalError::Model(
                "the map uses an onnx global model but names none".into(),
            )
        })?;
        OnnxGlobal::load(&p, runtime, None, Some(dim))
    })
}

/// Size and modification time of a file (`None` when unreadable).
pub fn file_stamp(path: &Path) -> Option<(u64, std::time::SystemTime)> {
    let m = std::fs::metadata(path).ok()?;
    Some((m.len(), m.modified().ok()?))
}

/// Why a map could not be prepared for serving.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    /// The file cannot be read or is not a usable map.
    #[error("{0}")]
    Map(String),
    /// The map cannot be served with this server's preset or models.
    #[error("{0}")]
    Serve(String),
}

impl Engine {
    /// Load every map of `s.db` and start `workers` worker threads (blocking; seconds).
    pub fn load(s: &Settings) -> Result<Self, String> {
        let runtime = RuntimeOptions {
            threads: s.ort_threads,
            device: s.device,
            ..RuntimeOptions::default()
        };
        let calibration = match &s.calibration {
            Some(p) => Some(Arc::new(
                pntr_pipeline::calibration::Calibration::load(p).map_err(|e| e.to_string())?,
            )),
            None => None,
        };
        let min_confidence = s.min_confidence;
        tracing::info!(
            calibration = %s.calibration.as_ref().map_or("each map's own, else the shipped one".into(), |p| p.display().to_string()),
            min_confidence = ?min_confidence,
            "confidence calibration"
        );
        let (tx, rx) = sync_channel::<Job>(s.queue);
        let mut engine = Self {
            maps: RwLock::new(Arc::new(Vec::new())),
            workers: s.workers,
            queue: s.queue,
            min_confidence,
            frame_convention: s.frame_convention,
            runtime,
            models: s.models.clone(),
            preset_override: s.preset.clone(),
            backbone_precision: s.backbone_precision,
            calibration,
            stages: Mutex::new(HashMap::new()),
            serial: AtomicU64::new(1),
            tx: Mutex::new(Some(tx)),
            queued: Arc::new(AtomicUsize::new(0)),
            busy: Arc::new(AtomicUsize::new(0)),
            threads: Mutex::new(Vec::new()),
        };
        let mut maps: Vec<Arc<LoadedMap>> = Vec::new();
        for path in &s.db {
            let m = engine.prepare(path).map_err(|e| e.to_string())?;
            if let Some(other) = maps.iter().find(|o| o.id == m.id) {
                return Err(format!(
                    "{} and {} both hold map `{}`: map ids must be unique",
                    other.file.display(),
                    path.display(),
                    m.id
                ));
            }
            maps.push(Arc::new(m));
        }
        *engine.maps.get_mut().unwrap_or_else(|e| e.into_inner()) = Arc::new(maps);
        let rx = Arc::new(Mutex::new(rx));
        let mut threads = Vec::new();
        for w in 0..s.workers {
            let rx = rx.clone();
            let counters = (engine.queued.clone(), engine.busy.clone());
            let t = std::thread::Builder::new()
                .name(format!("pntr-worker-{w}"))
                .spawn(move || worker(w, rx, counters))
                .map_err(|e| format!("starting worker {w}: {e}"))?;
            threads.push(t);
        }
        *engine.threads.get_mut().unwrap_or_else(|e| e.into_inner()) = threads;
        Ok(engine)
    }

    /// Read the map file at `path` and make it ready to serve: its preset checked against the
    /// server's, each worker's pipeline over it built (model sessions of a preset no loaded map used
    /// yet are created and warmed up). Blocking; seconds for a large map. Nothing is served from it
    /// until it is installed ([`Engine::install`]).
    pub fn prepare(&self, path: &Path) -> Result<LoadedMap, PrepareError> {
        let t = Instant::now();
        let map = load_map(path, &self.runtime)
            .map_err(|e| PrepareError::Map(format!("loading {}: {e}", path.display())))?;
        let id = map.header.map_id.clone();
        let points = map
            .images
            .iter()
            .map(|im| (im.scene, im.point))
            .collect::<BTreeSet<_>>()
            .len();
        let preset = match &self.preset_override {
            Some(name) => {
                Preset::named(name).map_err(|e| PrepareError::Serve(format!("--preset: {e}")))?
            }
            None => map.header.preset.clone(),
        };
        let built = &map.header.preset;
        preset.serves(built).map_err(|e| {
            PrepareError::Serve(format!(
                "--preset {} cannot serve map `{id}` ({}): {e}",
                preset.name,
                path.display()
            ))
        })?;
        if preset.name != built.name {
            tracing::info!(map_id = %id, built_with = %built.name,
                served_with = %preset.name, "map served with another preset of the same descriptors");
        }
        let (preset, stages) = self.fastest_stages(preset, &id)?;
        let map = Arc::new(map);
        let mut pipelines = Vec::with_capacity(stages.len());
        for stage in stages {
            let p = Pipeline::new(map.clone(), stage, preset.clone())
                .map_err(|e| PrepareError::Serve(format!("map `{id}`: {e}")))?;
            let p = match &self.calibration {
                Some(c) => p.with_calibration(c.clone(), self.min_confidence),
                None => p.with_min_confidence(self.min_confidence),
            };
            let p = match pipelines.first() {
                Some(first) => p.sharing_coverage(first),
                None => p,
            };
            pipelines.push(p);
        }
        // The map's coverage (what a stream's tracked pose is judged by) is made in the
        // background, so the first tracked frame does not wait for it.
        if let Some(first) = pipelines.first() {
            let make = first.coverage_maker();
            let _ = std::thread::Builder::new()
                .name("pntr-coverage".into())
                .spawn(make);
        }
        let (min_confidence, calibration_source) = pipelines
            .first()
            .map(|p| (p.min_confidence(), p.calibration().1))
            .unwrap_or((
                f64::NAN,
                pntr_pipeline::calibration::CalibrationSource::Shipped,
            ));
        let calibration_stale = map.calibration_is_stale();
        if calibration_stale {
            tracing::warn!(map_id = %id, "the map's own calibration was fitted before the map was extended or merged; refit it with `pntr calibrate --db`");
        }
        let extractor_engine = pipelines.first().map_or("", |p| p.stage.extractor.engine());
        let version = MapVersion::of(&map);
        let serial = self.serial.fetch_add(1, Ordering::SeqCst);
        tracing::info!(map_id = %id, version = %version.label, images = map.images.len(),
            file = %path.display(), extractor = %preset.extractor, engine = extractor_engine,
            calibration = calibration_source.name(), min_confidence, calibration_stale,
            seconds = t.elapsed().as_secs_f64(), "map ready");
        Ok(LoadedMap {
            id,
            map,
            points,
            preset,
            extractor_engine,
            file: path.to_path_buf(),
            version,
            frame: serial,
            serial,
            file_stamp: file_stamp(path),
            min_confidence,
            calibration_source,
            calibration_stale,
            pipelines,
            _release: ReleaseMemory,
        })
    }

    /// The networks mapping loads for this engine's maps (extending a map, refitting its own
    /// calibration): the engine's models folder and device, each stage built anew. A mapping job is
    /// one long task, not one of many requests, so its networks get the machine's threads (up to
    /// 4; at least a worker's), as `pntr build-db` does: an extension on two cores took 1-2 s
    /// longer than `build-db --extend` with one thread (BENCHMARKS.md, "Merged maps and their own
    /// calibration").
    pub fn stages(&self) -> pntr_mapping::stages::Stages {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        pntr_mapping::stages::Stages {
            models: self.models.clone(),
            runtime: pntr_features::runtime::RuntimeOptions {
                threads: cores.min(4).max(self.runtime.threads),
                ..self.runtime.clone()
            },
        }
    }

    /// The feature stages `preset` runs with, or those of its bf16 twin ([`Preset::bf16_twin`])
    /// where `--backbone-precision auto` (the default) finds it faster here: no `--preset` given,
    /// the models on the CPU, a CPU with bfloat16 instructions
    /// ([`pntr_features::openvino::cpu_has_bf16`]), and OpenVINO loaded and inferring in bf16.
    /// When the twin cannot be built the float backbone serves, with a warning naming why.
    fn fastest_stages(
        &self,
        preset: Preset,
        id: &str,
    ) -> Result<(Preset, Vec<FeatureStage>), PrepareError> {
        let twin = preset.bf16_twin().filter(|_| {
            self.preset_override.is_none()
                && self.backbone_precision == BackbonePrecision::Auto
                && self.runtime.device == pntr_features::runtime::Device::Cpu
                && pntr_features::openvino::cpu_has_bf16()
        });
        if let Some(twin) = twin {
            match self.stages_for(&twin) {
                Ok(stages)
                    if stages
                        .iter()
                        .all(|s| s.extractor.engine() == "openvino-bf16") =>
                {
                    tracing::info!(map_id = %id, built_with = %preset.name, served_with = %twin.name,
                        "the CPU has bfloat16 instructions: queries run the backbone in bf16 (--backbone-precision f32 keeps float)");
                    return Ok((twin, stages));
                }
                Ok(stages) => tracing::warn!(map_id = %id,
                    engine = stages.first().map_or("", |s| s.extractor.engine()),
                    "OpenVINO does not infer in bf16 on this CPU: queries run the float backbone"),
                Err(e) => tracing::warn!(map_id = %id, error = %e,
                    "the bf16 backbone cannot be loaded: queries run the float backbone"),
            }
        }
        let stages = self.stages_for(&preset).map_err(PrepareError::Serve)?;
        Ok((preset, stages))
    }

    /// Every worker's feature stage for `preset`, built (and warmed up) on first use.
    fn stages_for(&self, preset: &Preset) -> Result<Vec<FeatureStage>, String> {
        let key = (
            preset.extractor.clone(),
            preset.matcher.clone(),
            preset.extractor_top_k(),
        );
        let mut stages = self.stages.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(s) = stages.get(&key) {
            return Ok(s.clone());
        }
        let mut built = Vec::with_capacity(self.workers);
        for _ in 0..self.workers {
            let cfg = pntr_features::config::FeatureConfig {
                runtime: self.runtime.clone(),
                ..preset.feature_config(self.models.clone())
            };
            let st = cfg.build().map_err(|e| {
                format!(
                    "loading the models of preset {} from {}: {e}",
                    preset.name,
                    self.models.display()
                )
            })?;
            st.warm_up()
                .map_err(|e| format!("warming up the models of preset {}: {e}", preset.name))?;
            built.push(st);
        }
        stages.insert(key, built.clone());
        Ok(built)
    }

    /// The loaded maps now (a snapshot: later changes do not affect it).
    pub fn maps(&self) -> Arc<Vec<Arc<LoadedMap>>> {
        self.maps.read().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Swap in `map`. With `replacing` the loaded map of that id is replaced (it must be loaded, and
    /// `map` must hold the same id) and returned; without, `map`'s id must not be loaded yet. The
    /// change is one pointer swap: a request resolves its map once, so it runs on either the old map
    /// or the new one.
    pub fn install(
        &self,
        map: LoadedMap,
        replacing: Option<&str>,
    ) -> Result<Option<Arc<LoadedMap>>, InstallError> {
        let mut guard = self.maps.write().unwrap_or_else(|e| e.into_inner());
        let mut next: Vec<Arc<LoadedMap>> = guard.as_ref().clone();
        let at = next.iter().position(|m| m.id == map.id);
        let old = match (replacing, at) {
            (None, Some(_)) => return Err(InstallError::Exists(map.id)),
            (None, None) => {
                telemetry::register_map(&map.id);
                next.push(Arc::new(map));
                None
            }
            (Some(id), _) if id != map.id => {
                return Err(InstallError::OtherId {
                    wanted: id.to_string(),
                    found: map.id,
                    file: map.file,
                })
            }
            (Some(id), None) => return Err(InstallError::Missing(id.to_string())),
            (Some(_), Some(i)) => Some(std::mem::replace(&mut next[i], Arc::new(map))),
        };
        self.prune_stages(&next);
        *guard = Arc::new(next);
        Ok(old)
    }

    /// Forget the feature stages no map in `maps` uses (a replacement that brought another preset):
    /// jobs still running on the old map hold their own references until they are done.
    fn prune_stages(&self, maps: &[Arc<LoadedMap>]) {
        let used: BTreeSet<StageKey> = maps
            .iter()
            .map(|m| {
                (
                    m.preset.extractor.clone(),
                    m.preset.matcher.clone(),
                    m.preset.extractor_top_k(),
                )
            })
            .collect();
        self.stages
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .retain(|k, _| used.contains(k));
    }

    /// Stop serving map `id`; returns it (freed once its last job is done).
    pub fn remove(&self, id: &str) -> Result<Arc<LoadedMap>, InstallError> {
        let mut guard = self.maps.write().unwrap_or_else(|e| e.into_inner());
        let mut next: Vec<Arc<LoadedMap>> = guard.as_ref().clone();
        let i = next
            .iter()
            .position(|m| m.id == id)
            .ok_or_else(|| InstallError::Missing(id.to_string()))?;
        let old = next.remove(i);
        self.prune_stages(&next);
        *guard = Arc::new(next);
        Ok(old)
    }

    /// The map a request names (empty = the only one).
    pub fn resolve(&self, id: &str) -> Result<Arc<LoadedMap>, tonic::Status> {
        let maps = self.maps();
        let ids = || {
            maps.iter()
                .map(|m| m.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        if maps.is_empty() {
            return Err(tonic::Status::not_found(
                "this server holds no map now (all were unloaded): load one with MapAdmin",
            ));
        }
        if id.is_empty() {
            return if maps.len() == 1 {
                Ok(maps[0].clone())
            } else {
                Err(tonic::Status::invalid_argument(format!(
                    "map_id is empty but this server holds {} maps ({}): name one",
                    maps.len(),
                    ids()
                )))
            };
        }
        maps.iter().find(|m| m.id == id).cloned().ok_or_else(|| {
            tonic::Status::not_found(format!("no map `{id}` on this server (maps: {})", ids()))
        })
    }

    /// Queue a job, or refuse at once when the queue is full.
    pub fn submit(&self, job: Job) -> Result<(), SubmitError> {
        let guard = self.tx.lock().unwrap_or_else(|e| e.into_inner());
        let Some(tx) = guard.as_ref() else {
            return Err(SubmitError::Closed);
        };
        // Count first so a worker that takes the job at once never sees the counter below zero.
        // The gauge moves by increments, not by setting a value read earlier: those commute, so a
        // worker taking the job between the two steps cannot leave a stale depth behind.
        self.queued.fetch_add(1, Ordering::SeqCst);
        metrics::gauge!(telemetry::QUEUE_DEPTH).increment(1.0);
        match tx.try_send(job) {
            Ok(()) => Ok(()),
            Err(e) => {
                self.queued.fetch_sub(1, Ordering::SeqCst);
                metrics::gauge!(telemetry::QUEUE_DEPTH).decrement(1.0);
                Err(match e {
                    TrySendError::Full(_) => SubmitError::Full,
                    TrySendError::Disconnected(_) => SubmitError::Closed,
                })
            }
        }
    }

    /// Requests waiting for a worker now.
    pub fn queued(&self) -> usize {
        self.queued.load(Ordering::SeqCst)
    }

    /// Jobs a worker is running now.
    pub fn busy(&self) -> usize {
        self.busy.load(Ordering::SeqCst)
    }

    /// Stop taking jobs; workers finish what is queued and exit. `wait` joins them.
    pub fn close(&self, wait: bool) {
        self.tx.lock().unwrap_or_else(|e| e.into_inner()).take();
        if wait {
            let threads =
                std::mem::take(&mut *self.threads.lock().unwrap_or_else(|e| e.into_inner()));
            for t in threads {
                let _ = t.join();
            }
        }
    }
}

impl Drop for Engine {
    fn drop(&mut self) {
        self.close(false);
    }
}

/// Decrements the busy counter however a job ends.
struct Busy<'a>(&'a AtomicUsize);

impl Drop for Busy<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
        metrics::gauge!(telemetry::BUSY_WORKERS).decrement(1.0);
    }
}

fn worker(
    index: usize,
    rx: Arc<Mutex<Receiver<Job>>>,
    (queued, busy): (Arc<AtomicUsize>, Arc<AtomicUsize>),
) {
    loop {
        // The lock is held only while waiting for the next job, never while working.
        let job = {
            let rx = rx.lock().unwrap_or_else(|e| e.into_inner());
            rx.recv()
        };
        let Ok(job) = job else {
            return; // closed and drained
        };
        busy.fetch_add(1, Ordering::SeqCst);
        metrics::gauge!(telemetry::BUSY_WORKERS).increment(1.0);
        let guard = Busy(&busy);
        queued.fetch_sub(1, Ordering::SeqCst);
        metrics::gauge!(telemetry::QUEUE_DEPTH).decrement(1.0);
        let Job {
            map,
            query,
            options,
            deadline,
            enqueued,
            span,
            reply,
        } = job;
        let outcome = span.in_scope(|| {
            run(
                &map.pipelines[index],
                &query,
                &options,
                deadline,
                enqueued,
                &reply,
            )
        });
        // Stage times are recorded here, for every frame a worker localized, whether or not its
        // caller is still there to hear the answer: they describe the work done.
        if let Some(Outcome::Done {
            result: Ok(loc),
            queued,
        }) = &outcome
        {
            record_stages(loc, *queued, &map.id);
        }
        // The worker counts as free before the caller hears back.
        drop(guard);
        // The job's hold on its map ends here, before the reply.
        drop(map);
        if let Some(o) = outcome {
            let _ = reply.send(o);
        }
    }
}

/// Seconds per stage of one localized frame, in the order the response lists them.
pub fn stage_seconds(loc: &Localization, queued: Duration) -> [(&'static str, f64); 8] {
    let t = &loc.times;
    [
        ("queue", queued.as_secs_f64()),
        ("resampling", t.resampling),
        ("extraction", t.extraction),
        ("retrieval", t.retrieval),
        ("matching", t.matching),
        ("registration", t.registration),
        ("verification", t.verification),
        ("total", t.total),
    ]
}

fn record_stages(loc: &Localization, queued: Duration, map_id: &str) {
    for (stage, s) in stage_seconds(loc, queued) {
        metrics::histogram!(telemetry::STAGE_DURATION, "stage" => stage, "map_id" => map_id.to_string())
            .record(s);
    }
}

/// Run one job unless its caller is gone (`None`) or its deadline passed.
fn run(
    pipeline: &Pipeline,
    query: &Query,
    options: &LocalizeOptions,
    deadline: Option<Instant>,
    enqueued: Instant,
    reply: &oneshot::Sender<Outcome>,
) -> Option<Outcome> {
    let queued = enqueued.elapsed();
    if reply.is_closed() {
        tracing::debug!("caller gone before a worker was free; dropped");
        return None;
    }
    if deadline.is_some_and(|d| Instant::now() >= d) {
        tracing::info!(
            queued_ms = queued.as_secs_f64() * 1e3,
            "deadline passed while queued; dropped"
        );
        return Some(Outcome::Expired { queued });
    }
    Some(
        match std::panic::catch_unwind(AssertUnwindSafe(|| pipeline.localize_with(query, options)))
        {
            Ok(result) => Outcome::Done {
                result: result.map(Box::new),
                queued,
            },
            Err(p) => {
                let message = p
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                tracing::error!(%message, "the pipeline panicked");
                Outcome::Panicked { message }
            }
        },
    )
}
