//! Starting and stopping a server: bind, serve health at once, load in the background, flip health to
//! SERVING, and on shutdown stop accepting and drain within a time limit.
//!
//! Binding happens before loading (loading takes seconds), so orchestrators see a live process whose
//! health says NOT_SERVING rather than a refused port, and `127.0.0.1:0` can be reported right away.
//! A load failure stops the server with the error (the binary exits non-zero).

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Identity, Server, ServerTlsConfig};
use tonic_health::ServingStatus;

use crate::admin::{AdminGate, MapAdminService};
use crate::config::{ConfigError, Settings};
use crate::decode::Limits;
use crate::engine::Engine;
use crate::proto;
use crate::service::{Gate, LocalizerService, State};
use crate::telemetry;

/// The gRPC name of the localizer service (for health checks).
pub const SERVICE_NAME: &str = "pntr.v1.Localizer";
/// The gRPC name of the map administration service.
pub const ADMIN_SERVICE_NAME: &str = "pntr.v1.MapAdmin";

/// Why a server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// Invalid settings.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// An address could not be bound.
    #[error("binding {what} address {addr}: {message}")]
    Bind {
        /// `gRPC` or `metrics`.
        what: &'static str,
        /// The address.
        addr: SocketAddr,
        /// The OS error.
        message: String,
    },
    /// TLS files could not be used.
    #[error("TLS: {0}")]
    Tls(String),
    /// Maps or models could not be loaded.
    #[error("loading: {0}")]
    Load(String),
    /// Metrics could not be set up.
    #[error("metrics: {0}")]
    Metrics(String),
    /// The transport failed.
    #[error("serving: {0}")]
    Serve(String),
}

/// Whether the maps and models are loaded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LoadState {
    /// Still loading.
    Loading,
    /// Serving.
    Ready,
    /// Loading failed (the server stops).
    Failed(String),
}

/// A started server. Dropping it does not stop the server: call [`Running::shutdown`] and
/// [`Running::wait`].
#[derive(Debug)]
pub struct Running {
    /// The bound gRPC address.
    pub addr: SocketAddr,
    /// The bound `/metrics` address.
    pub metrics_addr: SocketAddr,
    /// The bound address of the live Foxglove view (`--foxglove`), when on.
    pub foxglove_addr: Option<SocketAddr>,
    /// Shared state (the engine once loaded).
    pub state: Arc<State>,
    shutdown: watch::Sender<bool>,
    load: watch::Receiver<LoadState>,
    task: Option<JoinHandle<Result<(), ServerError>>>,
}

impl Running {
    /// Begin a graceful shutdown: stop accepting, let in-flight requests finish within the drain
    /// timeout, stop the workers.
    pub fn shutdown(&self) {
        let _ = self.shutdown.send(true);
    }

    /// Read every loaded map's file again and replace those that changed, atomically, as
    /// `MapAdmin.ReloadMaps` does (SIGHUP). Refused while the server is still loading.
    pub async fn reload(&self) -> Result<proto::ReloadMapsResponse, crate::admin::AdminError> {
        crate::admin::reload(&self.state).await
    }

    /// Wait until the maps and models are loaded (Ok) or loading failed (Err).
    pub async fn ready(&self) -> Result<(), ServerError> {
        let mut rx = self.load.clone();
        let s = rx
            .wait_for(|s| *s != LoadState::Loading)
            .await
            .map(|s| s.clone())
            .unwrap_or(LoadState::Failed("the server stopped".into()));
        match s {
            LoadState::Ready => Ok(()),
            LoadState::Failed(m) => Err(ServerError::Load(m)),
            LoadState::Loading => unreachable!("waited for a change"),
        }
    }

    /// Wait for the server to stop (after [`Running::shutdown`], or on a fatal error). Cancel-safe.
    pub async fn wait(&mut self) -> Result<(), ServerError> {
        let Some(task) = self.task.as_mut() else {
            return Ok(());
        };
        let r = task.await;
        self.task = None;
        r.unwrap_or_else(|e| Err(ServerError::Serve(format!("server task: {e}"))))
    }
}

async fn bind(what: &'static str, addr: SocketAddr) -> Result<TcpListener, ServerError> {
    TcpListener::bind(addr)
        .await
        .map_err(|e| ServerError::Bind {
            what,
            addr,
            message: e.to_string(),
        })
}

/// Validate, bind both ports, start serving (health NOT_SERVING, Localize UNAVAILABLE) and load the
/// maps and models in the background. Returns once the ports are bound. Needs a Tokio runtime.
pub async fn start(settings: Settings) -> Result<Running, ServerError> {
    settings.validate()?;
    // Cheap checks of every map file before binding anything: a wrong path or an old format fails now.
    for p in &settings.db {
        pntr_pipeline::mapfile::read_header(p).map_err(|e| ServerError::Load(e.to_string()))?;
    }
    let tls = match &settings.tls {
        Some((cert, key)) => {
            let read = |p: &std::path::Path| {
                std::fs::read(p).map_err(|e| ServerError::Tls(format!("{}: {e}", p.display())))
            };
            Some(ServerTlsConfig::new().identity(Identity::from_pem(read(cert)?, read(key)?)))
        }
        None => None,
    };
    let prometheus = telemetry::prometheus().map_err(ServerError::Metrics)?;
    let listener = bind("gRPC", settings.addr).await?;
    let metrics_listener = bind("metrics", settings.metrics_addr).await?;
    let addr = listener
        .local_addr()
        .map_err(|e| ServerError::Serve(e.to_string()))?;
    let metrics_addr = metrics_listener
        .local_addr()
        .map_err(|e| ServerError::Serve(e.to_string()))?;

    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_service_status("", ServingStatus::NotServing)
        .await;
    health
        .set_service_status(SERVICE_NAME, ServingStatus::NotServing)
        .await;

    let (shutdown, shutdown_rx) = watch::channel(false);
    let state = Arc::new(State::new(
        Limits {
            max_width: settings.max_image_width,
            max_height: settings.max_image_height,
        },
        settings.workers.max(2),
        settings.max_streams,
        shutdown_rx.clone(),
    ));
    let foxglove_addr = match settings.foxglove {
        Some(a) => {
            let live =
                crate::visual::Live::start(a)
                    .await
                    .map_err(|message| ServerError::Bind {
                        what: "Foxglove",
                        addr: a,
                        message,
                    })?;
            let bound = live.addr();
            state.set_live(live);
            tokio::spawn(show_map_cameras(state.clone(), shutdown_rx.clone()));
            Some(bound)
        }
        None => None,
    };
    let gate = Gate::new(settings.token.as_deref());
    let admin = proto::map_admin_server::MapAdminServer::new(MapAdminService::new(state.clone()));
    let localizer =
        proto::localizer_server::LocalizerServer::new(LocalizerService::new(state.clone()))
            .max_decoding_message_size(settings.max_message_bytes)
            .max_encoding_message_size(settings.max_message_bytes);
    // Both reflection versions: `v1` for current tools, `v1alpha` for older grpcurl, Python's
    // grpcio-reflection and several GUI clients, which speak only that one.
    let reflection_builder = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection = reflection_builder()
        .build_v1()
        .map_err(|e| ServerError::Serve(format!("reflection v1: {e}")))?;
    let reflection_v1alpha = reflection_builder()
        .build_v1alpha()
        .map_err(|e| ServerError::Serve(format!("reflection v1alpha: {e}")))?;

    let mut builder = Server::builder()
        .max_concurrent_streams(Some(settings.max_streams_per_connection))
        .http2_keepalive_interval(settings.keepalive_interval)
        .http2_keepalive_timeout(Some(settings.keepalive_timeout));
    if let Some(tls) = tls {
        builder = builder
            .tls_config(tls)
            .map_err(|e| ServerError::Tls(e.to_string()))?;
    }
    let router = builder
        .add_service(health_service)
        .add_service(InterceptedService::new(localizer, gate.clone()))
        .add_service(InterceptedService::new(
            admin,
            AdminGate::new(settings.admin_token.as_deref()),
        ))
        .add_service(InterceptedService::new(reflection, gate.clone()))
        .add_service(InterceptedService::new(reflection_v1alpha, gate));

    let (load_tx, load_rx) = watch::channel(LoadState::Loading);
    let mut stop_serving = shutdown_rx.clone();
    let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
    let serve = tokio::spawn(async move {
        router
            .serve_with_incoming_shutdown(incoming, async move { stopped(&mut stop_serving).await })
            .await
    });
    let maps_state = state.clone();
    let metrics_task = tokio::spawn(telemetry::serve_metrics(
        metrics_listener,
        prometheus,
        shutdown_rx.clone(),
        Arc::new(move || {
            maps_state.engine().map_or_else(Vec::new, |e| {
                e.maps()
                    .iter()
                    .map(|m| telemetry::MapSeries {
                        map_id: m.id.clone(),
                        version: m.version.label.clone(),
                        images: m.map.images.len(),
                        calibration_stale: m.calibration_stale,
                        heap_bytes: m.map.heap_bytes(),
                    })
                    .collect()
            })
        }),
    ));

    let task = tokio::spawn(supervise(Supervised {
        settings,
        state: state.clone(),
        health,
        shutdown: shutdown.clone(),
        shutdown_rx,
        load_tx,
        serve,
        metrics_task,
    }));
    tracing::info!(%addr, %metrics_addr, "listening; loading maps and models");
    Ok(Running {
        addr,
        metrics_addr,
        foxglove_addr,
        state,
        shutdown,
        load: load_rx,
        task: Some(task),
    })
}

/// Every 2 s while a live Foxglove client listens, the poses of the loaded maps' images (a client
/// that connects later sees them within 2 s; the WebSocket protocol does not replay old messages).
async fn show_map_cameras(state: Arc<State>, mut stop: watch::Receiver<bool>) {
    loop {
        tokio::select! {
            _ = tokio::time::sleep(std::time::Duration::from_secs(2)) => {}
            _ = stopped(&mut stop) => return,
        }
        let (Some(live), Some(engine)) = (state.live(), state.engine()) else {
            continue;
        };
        if !live.view().wanted() {
            continue;
        }
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let maps = engine.maps();
        let poses = maps.iter().flat_map(|m| {
            let frames = crate::wire::MapFrames::of(&m.map.header);
            m.map
                .images
                .iter()
                .map(move |im| frames.pose_to_ros(&im.world_from_camera))
        });
        live.view().map_cameras(now, poses);
    }
}

struct Supervised {
    settings: Settings,
    state: Arc<State>,
    health: tonic_health::server::HealthReporter,
    shutdown: watch::Sender<bool>,
    shutdown_rx: watch::Receiver<bool>,
    load_tx: watch::Sender<LoadState>,
    serve: JoinHandle<Result<(), tonic::transport::Error>>,
    metrics_task: JoinHandle<()>,
}

fn serve_result(
    r: Result<Result<(), tonic::transport::Error>, tokio::task::JoinError>,
) -> Result<(), ServerError> {
    match r {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(ServerError::Serve(e.to_string())),
        Err(e) => Err(ServerError::Serve(e.to_string())),
    }
}

/// Resolves once shutdown is requested (without holding the channel's lock across an await).
pub(crate) async fn stopped(rx: &mut watch::Receiver<bool>) {
    let _ = rx.wait_for(|v| *v).await;
}

async fn supervise(mut s: Supervised) -> Result<(), ServerError> {
    let settings = s.settings.clone();
    let mut load = tokio::task::spawn_blocking(move || Engine::load(&settings));
    let mut stop = s.shutdown_rx.clone();
    let mut failure = None;
    // Phase 1: loading (a shutdown request meanwhile skips straight to draining).
    tokio::select! {
        r = &mut load => match r {
            Ok(Ok(engine)) => {
                s.state.set_engine(Arc::new(engine));
                s.health.set_service_status("", ServingStatus::Serving).await;
                s.health.set_service_status(SERVICE_NAME, ServingStatus::Serving).await;
                let _ = s.load_tx.send(LoadState::Ready);
                tracing::info!("maps and models loaded; serving");
            }
            Ok(Err(m)) => failure = Some(m),
            Err(e) => failure = Some(format!("the loader panicked: {e}")),
        },
        _ = stopped(&mut stop) => {}
        r = &mut s.serve => {
            let _ = s.load_tx.send(LoadState::Failed("the transport stopped".into()));
            s.metrics_task.abort();
            return serve_result(r);
        }
    }
    if let Some(m) = failure {
        tracing::error!(error = %m, "loading failed; stopping");
        let _ = s.load_tx.send(LoadState::Failed(m.clone()));
        let _ = s.shutdown.send(true);
        let _ = s.serve.await;
        s.metrics_task.abort();
        return Err(ServerError::Load(m));
    }
    // Phase 2: serving until asked to stop.
    let early = tokio::select! {
        _ = stopped(&mut stop) => None,
        r = &mut s.serve => Some(serve_result(r)),
    };
    s.health
        .set_service_status("", ServingStatus::NotServing)
        .await;
    s.health
        .set_service_status(SERVICE_NAME, ServingStatus::NotServing)
        .await;
    if s.load_tx.borrow().clone() == LoadState::Loading {
        let _ = s
            .load_tx
            .send(LoadState::Failed("shut down while loading".into()));
    }
    let result = match early {
        Some(r) => r,
        None => {
            tracing::info!(
                timeout_s = s.settings.drain_timeout.as_secs_f64(),
                "shutting down: no new connections; draining in-flight requests"
            );
            match tokio::time::timeout(s.settings.drain_timeout, &mut s.serve).await {
                Ok(r) => serve_result(r),
                Err(_) => {
                    let left = s.state.engine().map_or(0, |e| e.queued());
                    tracing::warn!(
                        queued = left,
                        "drain timeout: abandoning unfinished requests"
                    );
                    s.serve.abort();
                    Ok(())
                }
            }
        }
    };
    if let Some(engine) = s.state.engine() {
        engine.close(false);
    }
    s.metrics_task.abort();
    tracing::info!("stopped");
    result
}
