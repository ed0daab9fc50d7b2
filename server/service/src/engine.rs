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
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
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

use crate::config::Settings;
use crate::telemetry;

/// One loaded map.
#[derive(Debug)]
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
}

/// A frame waiting for a worker.
pub struct Job {
    /// Index into [`Engine::maps`].
    pub map: usize,
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

/// Why a job was not queued.
#[derive(Debug, PartialEq, Eq)]
pub enum SubmitError {
    /// The queue is full.
    Full,
    /// The pool is shutting down.
    Closed,
}

/// The maps and the worker pool.
pub struct Engine {
    /// Loaded maps, in `--db` order.
    pub maps: Vec<LoadedMap>,
    /// Worker threads.
    pub workers: usize,
    /// Queue capacity.
    pub queue: usize,
    /// The LOCALIZED threshold on the calibrated confidence.
    pub min_confidence: f64,
    tx: Mutex<Option<SyncSender<Job>>>,
    queued: Arc<AtomicUsize>,
    busy: Arc<AtomicUsize>,
    threads: Mutex<Vec<JoinHandle<()>>>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ids: Vec<&str> = self.maps.iter().map(|m| m.id.as_str()).collect();
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

impl Engine {
    /// Load every map and build `workers` sets of pipelines (blocking; seconds).
    pub fn load(s: &Settings) -> Result<Self, String> {
        let runtime = RuntimeOptions {
            threads: s.ort_threads,
            device: s.device,
            ..RuntimeOptions::default()
        };
        let mut maps: Vec<LoadedMap> = Vec::new();
        for path in &s.db {
            let t = Instant::now();
            let map =
                load_map(path, &runtime).map_err(|e| format!("loading {}: {e}", path.display()))?;
            let id = map.header.map_id.clone();
            if let Some(other) = maps.iter().position(|m| m.id == id) {
                return Err(format!(
                    "{} and {} both hold map `{id}`: map ids must be unique",
                    s.db[other].display(),
                    path.display()
                ));
            }
            let points = map
                .images
                .iter()
                .map(|im| (im.scene, im.point))
                .collect::<BTreeSet<_>>()
                .len();
            tracing::info!(map_id = %id, images = map.images.len(), file = %path.display(),
                seconds = t.elapsed().as_secs_f64(), "map loaded");
            let preset = match &s.preset {
                Some(name) => Preset::named(name).map_err(|e| format!("--preset: {e}"))?,
                None => map.header.preset.clone(),
            };
            let built = &map.header.preset;
            preset.serves(built).map_err(|e| {
                format!(
                    "--preset {} cannot serve map `{id}` ({}): {e}",
                    preset.name,
                    path.display()
                )
            })?;
            if preset.name != built.name {
                tracing::info!(map_id = %id, built_with = %built.name,
                    served_with = %preset.name, "map served with another preset of the same descriptors");
            }
            maps.push(LoadedMap {
                id,
                map: Arc::new(map),
                points,
                preset,
                extractor_engine: "",
            });
        }
        let calibration = Arc::new(match &s.calibration {
            Some(p) => {
                pntr_pipeline::calibration::Calibration::load(p).map_err(|e| e.to_string())?
            }
            None => pntr_pipeline::calibration::Calibration::embedded(),
        });
        let min_confidence = s.min_confidence.unwrap_or(calibration.threshold);
        tracing::info!(
            calibration = %s.calibration.as_ref().map_or("embedded".into(), |p| p.display().to_string()),
            min_confidence,
            "confidence calibration"
        );
        // One set of pipelines per worker; maps built with the same preset share the worker's stage.
        let mut per_worker: Vec<Vec<Pipeline>> = Vec::with_capacity(s.workers);
        for w in 0..s.workers {
            let mut stages: HashMap<(String, String, usize), FeatureStage> = HashMap::new();
            let mut pipelines = Vec::with_capacity(maps.len());
            for m in &maps {
                let preset = m.preset.clone();
                let key = (
                    preset.extractor.clone(),
                    preset.matcher.clone(),
                    preset.keypoints,
                );
                let stage = match stages.get(&key) {
                    Some(st) => st.clone(),
                    None => {
                        let cfg = pntr_features::config::FeatureConfig {
                            runtime: runtime.clone(),
                            ..preset.feature_config(s.models.clone())
                        };
                        let st = cfg.build().map_err(|e| {
                            format!(
                                "loading the models of preset {} from {}: {e}",
                                preset.name,
                                s.models.display()
                            )
                        })?;
                        st.warm_up().map_err(|e| {
                            format!("warming up the models of preset {}: {e}", preset.name)
                        })?;
                        stages.insert(key, st.clone());
                        st
                    }
                };
                let p = Pipeline::new(m.map.clone(), stage, preset)
                    .map_err(|e| format!("map `{}`: {e}", m.id))?
                    .with_calibration(calibration.clone(), Some(min_confidence));
                pipelines.push(p);
            }
            tracing::debug!(worker = w, "pipelines ready");
            per_worker.push(pipelines);
        }
        if let Some(first) = per_worker.first() {
            for (m, p) in maps.iter_mut().zip(first) {
                m.extractor_engine = p.stage.extractor.engine();
                tracing::info!(map_id = %m.id, extractor = %m.preset.extractor,
                    engine = m.extractor_engine, "extractor ready");
            }
        }
        let (tx, rx) = sync_channel::<Job>(s.queue);
        let rx = Arc::new(Mutex::new(rx));
        let queued = Arc::new(AtomicUsize::new(0));
        let busy = Arc::new(AtomicUsize::new(0));
        let mut threads = Vec::new();
        for (w, pipelines) in per_worker.into_iter().enumerate() {
            let rx = rx.clone();
            let counters = (queued.clone(), busy.clone());
            let t = std::thread::Builder::new()
                .name(format!("pntr-worker-{w}"))
                .spawn(move || worker(pipelines, rx, counters))
                .map_err(|e| format!("starting worker {w}: {e}"))?;
            threads.push(t);
        }
        Ok(Self {
            maps,
            workers: s.workers,
            queue: s.queue,
            min_confidence,
            tx: Mutex::new(Some(tx)),
            queued,
            busy,
            threads: Mutex::new(threads),
        })
    }

    /// The map a request names (empty = the only one).
    pub fn resolve(&self, id: &str) -> Result<usize, tonic::Status> {
        let ids = || {
            self.maps
                .iter()
                .map(|m| m.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        if id.is_empty() {
            return if self.maps.len() == 1 {
                Ok(0)
            } else {
                Err(tonic::Status::invalid_argument(format!(
                    "map_id is empty but this server holds {} maps ({}): name one",
                    self.maps.len(),
                    ids()
                )))
            };
        }
        self.maps.iter().position(|m| m.id == id).ok_or_else(|| {
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
    pipelines: Vec<Pipeline>,
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
                &pipelines[map],
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
            record_stages(loc, *queued);
        }
        // The worker counts as free before the caller hears back.
        drop(guard);
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

fn record_stages(loc: &Localization, queued: Duration) {
    for (stage, s) in stage_seconds(loc, queued) {
        metrics::histogram!(telemetry::STAGE_DURATION, "stage" => stage).record(s);
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
