//! `pntr.v1.MapAdmin`: load, replace, unload and reload maps while the server answers robots.
//!
//! A change reads and prepares the new map beside the old one (file checksums, preset, one pipeline
//! per worker) on a blocking thread, then swaps the engine's list of maps in one step
//! ([`crate::engine::Engine::install`]). Requests resolve their map once, so each runs wholly on the
//! old map or wholly on the new one; the old map is freed when the last request holding it is done.
//! Changes are applied one at a time (the state's admin lock), whether they come from this API or
//! from SIGHUP ([`reload`]).
//!
//! Admin calls need their own token (`pntr-server --admin-token`), checked by [`AdminGate`] before
//! the message is decoded; a server without one refuses every admin call.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use tonic::service::Interceptor;
use tonic::{Request, Response, Status};

use pntr_mapping::recording_map;

use crate::engine::{shares_frame, InstallError, LoadedMap, PrepareError};
use crate::proto;
use crate::service::State;

/// Checks the admin token on every MapAdmin call; without a configured token every call is refused.
#[derive(Clone, Default)]
pub struct AdminGate {
    token: Option<Arc<[u8]>>,
}

impl AdminGate {
    /// A gate requiring `authorization: Bearer <token>`; `None` refuses every call.
    pub fn new(token: Option<&str>) -> Self {
        Self {
            token: token.map(|t| Arc::from(format!("Bearer {t}").into_bytes())),
        }
    }
}

impl Interceptor for AdminGate {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        let Some(want) = &self.token else {
            return Err(Status::permission_denied(
                "map administration is off on this server: start pntr-server with --admin-token or --admin-token-file",
            ));
        };
        let got = req
            .metadata()
            .get("authorization")
            .map(|v| v.as_bytes())
            .unwrap_or_default();
        if !crate::service::same(got, want) {
            return Err(Status::unauthenticated(
                "missing or invalid admin token (send `authorization: Bearer <admin token>`; the clients' token is not the admin token)",
            ));
        }
        Ok(req)
    }
}

/// Why a map change was refused. Mapped to a gRPC status in one place ([`From<AdminError>`]).
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    /// The server has not finished loading.
    #[error("the server is still loading its maps and models")]
    Loading,
    /// A required field is empty.
    #[error("{0} is empty")]
    Missing(&'static str),
    /// The named file does not exist on the server.
    #[error("{0}: no such file on the server (paths are the server's; relative ones from its working folder)")]
    NoFile(PathBuf),
    /// The named path is a folder, a FIFO, a device ([`pntr_pipeline::mapfile::not_a_regular_file`]).
    #[error("{0} is {1}, not a map file: give a map file (`pntr build-db --out`)")]
    NotAFile(PathBuf, &'static str),
    /// The file could not be made ready to serve.
    #[error(transparent)]
    Prepare(#[from] PrepareError),
    /// The swap was refused.
    #[error(transparent)]
    Install(#[from] InstallError),
    /// The map's file no longer holds the loaded version.
    #[error("{file} changed since map `{map_id}` was loaded from it (reload it first, then extend)", file = .file.display())]
    Changed {
        /// The map.
        map_id: String,
        /// Its file.
        file: PathBuf,
    },
    /// The map could not be extended (a recording that cannot be read, nothing new kept).
    #[error("extending map `{map_id}`: {message}")]
    Extend {
        /// The map.
        map_id: String,
        /// Why.
        message: String,
    },
    /// A blocking task failed.
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<AdminError> for Status {
    fn from(e: AdminError) -> Self {
        let m = e.to_string();
        match e {
            AdminError::Loading => Status::unavailable(m),
            AdminError::Missing(_) | AdminError::NotAFile(..) => Status::invalid_argument(m),
            AdminError::NoFile(_) | AdminError::Install(InstallError::Missing(_)) => {
                Status::not_found(m)
            }
            AdminError::Install(InstallError::Exists(_)) => Status::already_exists(m),
            AdminError::Install(InstallError::OtherId { .. })
            | AdminError::Prepare(PrepareError::Map(_) | PrepareError::Serve(_))
            | AdminError::Changed { .. }
            | AdminError::Extend { .. } => Status::failed_precondition(m),
            AdminError::Internal(_) => Status::internal(m),
        }
    }
}

/// The entry a listing or a change reports for `m`.
pub fn entry(m: &LoadedMap) -> proto::LoadedMap {
    proto::LoadedMap {
        map_id: m.id.clone(),
        version: m.version.label.clone(),
        images: m.map.images.len() as u32,
        file: m.file.display().to_string(),
        preset: m.preset.name.clone(),
        built_at: m.version.built_at.clone(),
        heap_bytes: m.map.heap_bytes() as u64,
        calibration: Some(crate::service::calibration_info(m)),
    }
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<T, AdminError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| AdminError::Internal(e.to_string()))
}

/// Read and prepare the map at `file`, then swap it in: as a new map (`replacing` = `None`) or in
/// place of the loaded map `replacing`. The caller holds the admin lock.
async fn install(
    state: &State,
    file: PathBuf,
    replacing: Option<String>,
) -> Result<proto::MapChange, AdminError> {
    let engine = state.loaded().map_err(|_| AdminError::Loading)?.clone();
    if file.as_os_str().is_empty() {
        return Err(AdminError::Missing("file"));
    }
    match pntr_pipeline::mapfile::not_a_regular_file(&file) {
        None => {}
        Some("no such file") => return Err(AdminError::NoFile(file)),
        Some(what) => return Err(AdminError::NotAFile(file, what)),
    }
    if let Some(id) = &replacing {
        // Refused before minutes of loading when the map is not there to replace.
        if !engine.maps().iter().any(|m| &m.id == id) {
            return Err(InstallError::Missing(id.clone()).into());
        }
    }
    let t = Instant::now();
    blocking(move || {
        let mut new = engine.prepare(&file)?;
        let old = replacing
            .as_deref()
            .and_then(|id| engine.maps().iter().find(|m| m.id == id).cloned());
        let same_frame = old.as_ref().is_some_and(|o| {
            let same = shares_frame(&o.map, &new.map);
            if same {
                new.frame = o.frame;
            }
            same
        });
        let load_seconds = t.elapsed().as_secs_f64();
        let map = entry(&new);
        let id = new.id.clone();
        let replaced = engine.install(new, replacing.as_deref())?;
        let previous_version = replaced
            .as_ref()
            .map(|o| o.version.label.clone())
            .unwrap_or_default();
        tracing::info!(map_id = %id, version = %map.version, previous = %previous_version,
            same_frame, load_seconds, "map {}", if replaced.is_some() { "replaced" } else { "loaded" });
        // The old map is freed here when no request holds it, else by the last one that does.
        drop(old);
        drop(replaced);
        Ok(proto::MapChange {
            map: Some(map),
            previous_version,
            same_frame,
            load_seconds,
            images_added: 0,
        })
    })
    .await?
}

/// Load the map file `file` (its header names the id).
pub async fn load(state: &State, file: PathBuf) -> Result<proto::MapChange, AdminError> {
    let _one_at_a_time = state.admin.lock().await;
    install(state, file, None).await
}

/// Replace loaded map `map_id` by the map in `file`.
pub async fn replace(
    state: &State,
    map_id: String,
    file: PathBuf,
) -> Result<proto::MapChange, AdminError> {
    if map_id.is_empty() {
        return Err(AdminError::Missing("map_id"));
    }
    let _one_at_a_time = state.admin.lock().await;
    install(state, file, Some(map_id)).await
}

/// What [`extend`] adds to a map: recordings on the server and how to read them.
#[derive(Debug, Clone, Default)]
pub struct Extension {
    /// Recordings (TUM folders, rosbag2 folders, .mcap files).
    pub sequences: Vec<PathBuf>,
    /// Optional TUM trajectories, one per sequence.
    pub trajectories: Vec<PathBuf>,
    /// Units per metre of integer depth (`None`: the recording's own).
    pub depth_units_per_m: Option<f64>,
    /// A bag's topics and TF frames (the reader's defaults where not given).
    pub topics: pntr_dataset::bag::Topics,
}

/// Add the keyframes of `ext`'s recordings to loaded map `map_id`, write the result over the map's
/// file (atomically) and serve it in place of the loaded version.
pub async fn extend(
    state: &State,
    map_id: String,
    ext: Extension,
) -> Result<proto::MapChange, AdminError> {
    if map_id.is_empty() {
        return Err(AdminError::Missing("map_id"));
    }
    if ext.sequences.is_empty() {
        return Err(AdminError::Missing("sequence"));
    }
    let failed = {
        let map_id = map_id.clone();
        move |message: String| AdminError::Extend {
            map_id: map_id.clone(),
            message,
        }
    };
    if !ext.trajectories.is_empty() && ext.trajectories.len() != ext.sequences.len() {
        return Err(failed(format!(
            "{} trajectories for {} sequences: give one per sequence, or none",
            ext.trajectories.len(),
            ext.sequences.len()
        )));
    }
    if let Some(p) = ext
        .sequences
        .iter()
        .chain(&ext.trajectories)
        .find(|p| !p.exists())
    {
        return Err(AdminError::NoFile(p.clone()));
    }
    let _one_at_a_time = state.admin.lock().await;
    let engine = state.loaded().map_err(|_| AdminError::Loading)?.clone();
    let loaded = engine
        .resolve(&map_id)
        .map_err(|_| InstallError::Missing(map_id.clone()))?;
    let t = Instant::now();
    let file = loaded.file.clone();
    let checksum = loaded.version.checksum;
    drop(loaded);
    let (id, path) = (map_id.clone(), file.clone());
    let added = blocking(move || -> Result<usize, AdminError> {
        // The file, not the loaded map, is extended (the loaded one is shared and read-only); it
        // must still be the version being served.
        let base = pntr_pipeline::mapfile::load(&file, |_| {
            Err(pntr_retrieval::RetrievalError::Model(
                "extending a map with an onnx global descriptor is not supported".into(),
            ))
        })
        .map_err(|e| failed(format!("reading {}: {e}", file.display())))?;
        if base.checksum != checksum {
            return Err(AdminError::Changed {
                map_id: map_id.clone(),
                file: file.clone(),
            });
        }
        let before = base.images.len();
        let mut recordings = Vec::new();
        for (i, path) in ext.sequences.iter().enumerate() {
            let opts = pntr_dataset::recording::RecordingOptions {
                trajectory: ext.trajectories.get(i).cloned(),
                depth_units_per_m: ext.depth_units_per_m,
                topics: ext.topics.clone(),
                ..Default::default()
            };
            let rec = pntr_dataset::recording::Recording::open(path, &opts)
                .map_err(|e| failed(format!("{}: {e}", path.display())))?;
            let camera = rec.intrinsics().ok_or_else(|| {
                failed(format!(
                    "{}: {} (extend it with `pntr build-db --extend ... --intrinsics`)",
                    path.display(),
                    rec.camera_problem()
                        .unwrap_or_else(|| "no camera calibration".into())
                ))
            })?;
            recordings.push((rec, camera));
        }
        let sessions: Vec<_> = recordings
            .iter()
            .map(|(recording, camera)| pntr_mapping::recording_map::Session {
                recording,
                camera: *camera,
            })
            .collect();
        let map_id = base.header.map_id.clone();
        // The map's own calibration refitted on the frames given (at most
        // SELF_CALIBRATION_FRAMES between the new keyframes), as `build-db --extend` does, so the
        // map is never served with one fitted before it grew.
        let opts = pntr_mapping::from_recordings::Options {
            target: pntr_mapping::from_recordings::Target::Extend(base),
            keyframes: pntr_mapping::keyframes::KeyframeParams::default(),
            check: None,
            self_calibrate: true,
            self_calibration_frames: recording_map::SELF_CALIBRATION_FRAMES,
            base_calibration: pntr_pipeline::calibration::Calibration::embedded(),
        };
        let mut last_stage = String::new();
        let (map, report) = pntr_mapping::from_recordings::run(
            &sessions,
            opts,
            &engine.stages(),
            &mut |s| {
                if s.stage != last_stage {
                    tracing::info!(map_id = %map_id, stage = s.stage, "extending the map");
                    last_stage = s.stage.to_string();
                }
            },
        )
        .map_err(|e| failed(e.to_string()))?;
        // What build-db would print as warnings (frames left out, a pose source that disagrees
        // with the images, ...) goes to the server's log, where its operator reads.
        for w in &report.build.warnings {
            tracing::warn!(map_id = %map_id, warning = %w, "extending the map");
        }
        match &report.calibration_note {
            Some(why) => tracing::warn!(map_id = %map_id, why = %why,
                "the map keeps the calibration it had (GetMapInfo says it is stale when it was the map's own)"),
            None => tracing::info!(map_id = %map_id, seconds = report.self_calibration_seconds,
                "the map's own calibration refitted on the extension's frames"),
        }
        let added = map.images.len() - before;
        pntr_pipeline::mapfile::save(&map, &file)
            .map_err(|e| failed(format!("writing {}: {e}", file.display())))?;
        tracing::info!(map_id = %map.header.map_id, added, file = %file.display(), "map extended and written");
        Ok(added)
    })
    .await??;
    let mut change = install(state, path, Some(id)).await?;
    change.images_added = added as u32;
    change.load_seconds = t.elapsed().as_secs_f64();
    Ok(change)
}

/// Stop serving `map_id`.
pub async fn unload(state: &State, map_id: String) -> Result<proto::MapChange, AdminError> {
    if map_id.is_empty() {
        return Err(AdminError::Missing("map_id"));
    }
    let _one_at_a_time = state.admin.lock().await;
    let engine = state.loaded().map_err(|_| AdminError::Loading)?.clone();
    blocking(move || {
        let old = engine.remove(&map_id)?;
        tracing::info!(map_id = %old.id, version = %old.version.label, "map unloaded");
        Ok(proto::MapChange {
            map: Some(entry(&old)),
            ..proto::MapChange::default()
        })
    })
    .await?
}

/// Read every loaded map's file again and replace the maps whose file changed (size or
/// modification time), each the way [`replace`] does; a file that fails leaves its map as it was.
/// What SIGHUP runs.
pub async fn reload(state: &State) -> Result<proto::ReloadMapsResponse, AdminError> {
    let _one_at_a_time = state.admin.lock().await;
    let engine = state.loaded().map_err(|_| AdminError::Loading)?.clone();
    let mut out = proto::ReloadMapsResponse::default();
    for m in engine.maps().iter() {
        if m.file_stamp.is_some() && crate::engine::file_stamp(&m.file) == m.file_stamp {
            out.unchanged_map_ids.push(m.id.clone());
            continue;
        }
        match install(state, m.file.clone(), Some(m.id.clone())).await {
            Ok(c) => out.reloaded.push(c),
            Err(e) => {
                tracing::warn!(map_id = %m.id, file = %m.file.display(), error = %e,
                    "reload failed; the map keeps serving its loaded version");
                out.failed.push(format!("{}: {e}", m.id));
            }
        }
    }
    Ok(out)
}

/// The MapAdmin service.
#[derive(Debug, Clone)]
pub struct MapAdminService {
    state: Arc<State>,
}

impl MapAdminService {
    /// A service over `state`.
    pub fn new(state: Arc<State>) -> Self {
        Self { state }
    }
}

#[tonic::async_trait]
impl proto::map_admin_server::MapAdmin for MapAdminService {
    async fn list_maps(
        &self,
        _request: Request<proto::ListMapsRequest>,
    ) -> Result<Response<proto::ListMapsResponse>, Status> {
        let engine = self.state.loaded()?;
        Ok(Response::new(proto::ListMapsResponse {
            maps: engine.maps().iter().map(|m| entry(m)).collect(),
        }))
    }

    async fn load_map(
        &self,
        request: Request<proto::LoadMapRequest>,
    ) -> Result<Response<proto::MapChange>, Status> {
        let file = PathBuf::from(request.into_inner().file);
        Ok(Response::new(load(&self.state, file).await?))
    }

    async fn replace_map(
        &self,
        request: Request<proto::ReplaceMapRequest>,
    ) -> Result<Response<proto::MapChange>, Status> {
        let r = request.into_inner();
        Ok(Response::new(
            replace(&self.state, r.map_id, PathBuf::from(r.file)).await?,
        ))
    }

    async fn unload_map(
        &self,
        request: Request<proto::UnloadMapRequest>,
    ) -> Result<Response<proto::MapChange>, Status> {
        let id = request.into_inner().map_id;
        Ok(Response::new(unload(&self.state, id).await?))
    }

    async fn extend_map(
        &self,
        request: Request<proto::ExtendMapRequest>,
    ) -> Result<Response<proto::MapChange>, Status> {
        let r = request.into_inner();
        let defaults = pntr_dataset::bag::Topics::default();
        let or = |given: &str, default: String| {
            if given.is_empty() {
                default
            } else {
                given.to_string()
            }
        };
        let topics = pntr_dataset::bag::Topics {
            rgb: or(&r.rgb_topic, defaults.rgb),
            depth: or(&r.depth_topic, defaults.depth),
            info: or(&r.info_topic, defaults.info),
            pose: (!r.pose_topic.is_empty()).then(|| r.pose_topic.clone()),
            map_frame: or(&r.map_frame, defaults.map_frame),
            camera_frame: (!r.camera_frame.is_empty()).then(|| r.camera_frame.clone()),
        };
        let ext = Extension {
            sequences: r.sequence.iter().map(PathBuf::from).collect(),
            trajectories: r.trajectory.iter().map(PathBuf::from).collect(),
            depth_units_per_m: (r.depth_scale > 0.0).then_some(r.depth_scale),
            topics,
        };
        if !(r.depth_scale.is_finite() && r.depth_scale >= 0.0) {
            return Err(Status::invalid_argument(
                "depth_scale must be a positive number of units per metre, or 0",
            ));
        }
        Ok(Response::new(extend(&self.state, r.map_id, ext).await?))
    }

    async fn reload_maps(
        &self,
        _request: Request<proto::ReloadMapsRequest>,
    ) -> Result<Response<proto::ReloadMapsResponse>, Status> {
        Ok(Response::new(reload(&self.state).await?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn call(gate: &mut AdminGate, header: Option<&str>) -> Result<(), Status> {
        let mut req = Request::new(());
        if let Some(h) = header {
            req.metadata_mut()
                .insert("authorization", h.parse().unwrap());
        }
        gate.call(req).map(|_| ())
    }

    #[test]
    fn admin_calls_need_the_admin_token_and_a_server_that_has_one() {
        let mut off = AdminGate::new(None);
        for h in [None, Some("Bearer anything")] {
            let e = call(&mut off, h).unwrap_err();
            assert_eq!(e.code(), tonic::Code::PermissionDenied);
            assert!(e.message().contains("--admin-token"), "{}", e.message());
        }
        let mut on = AdminGate::new(Some("adm1n"));
        assert!(call(&mut on, Some("Bearer adm1n")).is_ok());
        for h in [
            None,
            Some("Bearer adm1"),
            Some("adm1n"),
            Some("Bearer adm1nn"),
        ] {
            let e = call(&mut on, h).unwrap_err();
            assert_eq!(e.code(), tonic::Code::Unauthenticated, "{h:?}");
            assert!(!e.message().contains("adm1n"), "{}", e.message());
        }
    }

    #[test]
    fn every_refusal_has_its_code() {
        let code = |e: AdminError| Status::from(e).code();
        use tonic::Code;
        assert_eq!(code(AdminError::Loading), Code::Unavailable);
        assert_eq!(code(AdminError::Missing("file")), Code::InvalidArgument);
        assert_eq!(code(AdminError::NoFile("x".into())), Code::NotFound);
        assert_eq!(
            code(InstallError::Missing("a".into()).into()),
            Code::NotFound
        );
        assert_eq!(
            code(InstallError::Exists("a".into()).into()),
            Code::AlreadyExists
        );
        assert_eq!(
            code(PrepareError::Map("bad".into()).into()),
            Code::FailedPrecondition
        );
    }
}
