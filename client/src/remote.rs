//! Talking to a running `pntr-server`: connection (plain or TLS), the bearer token, and the evaluation
//! view of a response. Used by `pntr eval --remote`, `pntr demo`, `pntr localize` and `pntr bench`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};
use pntr_eval::Answer;
use pntr_pipeline::pipeline::{Query, StageTimes, Status};
use pntr_pipeline::prior::{Mode, Region};
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::{self, LocalizeResponse};
use pntr_service::tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use pntr_service::{tokio, tonic, wire};

/// How to reach the server: address, TLS and token (the options every client command shares).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ConnectArgs {
    /// Server address, HOST:PORT (or a URL); several, comma-separated, are balanced per request.
    #[arg(long)]
    pub addr: String,
    /// Map id sent with every request (empty: the server's only map).
    #[arg(long, default_value = "")]
    pub map_id: String,
    /// Bearer token, when the server requires one (or PNTR_TOKEN).
    #[arg(long, env = "PNTR_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// PEM file of the CA that signed the server's certificate: connect with TLS.
    #[arg(long)]
    pub tls_ca: Option<PathBuf>,
    /// Name to verify in the server's certificate (default: the host of --addr).
    #[arg(long)]
    pub tls_domain: Option<String>,
}

/// Open a channel to the server. Several comma-separated addresses make one channel that balances
/// requests over all of them (client-side load balancing across replicas).
pub async fn channel(c: &ConnectArgs) -> Result<Channel> {
    let scheme = if c.tls_ca.is_some() { "https" } else { "http" };
    let mut endpoints = Vec::new();
    for addr in c.addr.split(',').map(str::trim).filter(|a| !a.is_empty()) {
        let url = if addr.contains("://") {
            addr.to_string()
        } else {
            format!("{scheme}://{addr}")
        };
        let mut ep = Endpoint::from_shared(url.clone())
            .with_context(|| format!("bad address {addr}"))?
            .connect_timeout(Duration::from_secs(10))
            .tcp_nodelay(true);
        if let Some(ca) = &c.tls_ca {
            let pem = std::fs::read(ca).with_context(|| format!("reading {}", ca.display()))?;
            let host = addr.rsplit_once(':').map(|(h, _)| h).unwrap_or(addr);
            let tls = ClientTlsConfig::new()
                .ca_certificate(Certificate::from_pem(pem))
                .domain_name(c.tls_domain.clone().unwrap_or_else(|| host.to_string()));
            ep = ep.tls_config(tls).context("TLS configuration")?;
        }
        endpoints.push((url, ep));
    }
    match endpoints.len() {
        0 => anyhow::bail!("no server address given"),
        1 => {
            let (url, ep) = endpoints.remove(0);
            ep.connect().await.with_context(|| {
                format!(
                    "cannot reach pntr-server at {url}{}",
                    tls_hint(c).unwrap_or_default()
                )
            })
        }
        _ => {
            // Fail early and clearly when a replica is down, rather than on some later request.
            for (url, ep) in &endpoints {
                ep.connect()
                    .await
                    .with_context(|| format!("cannot reach pntr-server at {url}"))?;
            }
            Ok(Channel::balance_list(
                endpoints.into_iter().map(|(_, ep)| ep),
            ))
        }
    }
}

/// When a plaintext connection fails because the server speaks TLS, say so: the server at `c.addr`
/// is probed with an HTTP/2 preface and a TLS server answers it with a TLS record (an alert, first
/// byte 0x15) rather than HTTP/2 frames. `None` with `--tls-ca` given or when the probe is not
/// conclusive.
pub fn tls_hint(c: &ConnectArgs) -> Option<String> {
    use std::io::{Read, Write};
    if c.tls_ca.is_some() {
        return None;
    }
    let addr = c.addr.split(',').next()?.trim();
    let addr = addr.split("://").last()?;
    let sock = std::net::ToSocketAddrs::to_socket_addrs(addr)
        .ok()?
        .next()?;
    let mut s = std::net::TcpStream::connect_timeout(&sock, Duration::from_secs(2)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(2))).ok()?;
    s.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n").ok()?;
    let mut first = [0u8; 1];
    s.read_exact(&mut first).ok()?;
    (first[0] == 0x15 || first[0] == 0x16).then(|| {
        ": the server expects TLS (it answered with a TLS record): connect with --tls-ca <the CA's PEM>".to_string()
    })
}

/// The error of a failed call, with the TLS hint when a plaintext call met a TLS server.
pub fn call_error(c: &ConnectArgs, s: &tonic::Status) -> anyhow::Error {
    let hint = matches!(
        s.code(),
        tonic::Code::Unavailable | tonic::Code::Unknown | tonic::Code::Internal
    )
    .then(|| tls_hint(c))
    .flatten()
    .unwrap_or_default();
    anyhow::anyhow!(
        "the server answered {}: {}{hint}",
        pntr_service::service::code_name(s.code()),
        s.message()
    )
}

/// A request with the map id and the token attached.
pub fn request(
    c: &ConnectArgs,
    mut req: proto::LocalizeRequest,
) -> Result<tonic::Request<proto::LocalizeRequest>> {
    req.map_id = c.map_id.clone();
    authorized(c, req)
}

/// Any request message (a single one or a stream) with the token attached, and the map id as
/// `x-pntr-map-id` metadata when one is given (for proxies that route by map).
pub fn authorized<T>(c: &ConnectArgs, message: T) -> Result<tonic::Request<T>> {
    let mut r = tonic::Request::new(message);
    if !c.map_id.is_empty() {
        r.metadata_mut().insert(
            pntr_service::service::MAP_ID_HEADER,
            c.map_id.parse().with_context(|| {
                format!("--map-id {:?} is not valid in an HTTP header", c.map_id)
            })?,
        );
    }
    if let Some(t) = &c.token {
        r.metadata_mut().insert(
            "authorization",
            format!("Bearer {t}")
                .parse()
                .context("the token is not valid in an HTTP header")?,
        );
    }
    Ok(r)
}

/// A gRPC client with its message limits raised for full-size frames.
pub fn client(ch: Channel) -> LocalizerClient<Channel> {
    LocalizerClient::new(ch)
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20)
}

/// A blocking client over a small Tokio runtime of its own.
pub struct Remote {
    rt: tokio::runtime::Runtime,
    client: LocalizerClient<Channel>,
    connect: ConnectArgs,
    /// Frames of the map's answers (GetMapInfo), asked once.
    frames: Option<wire::MapFrames>,
}

impl Remote {
    /// Connect.
    pub fn connect(c: &ConnectArgs) -> Result<Self> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let ch = rt.block_on(channel(c))?;
        Ok(Self {
            rt,
            client: client(ch),
            connect: c.clone(),
            frames: None,
        })
    }

    /// Send one request and wait for the answer.
    pub fn send(&mut self, req: proto::LocalizeRequest) -> Result<LocalizeResponse, tonic::Status> {
        let r = request(&self.connect, req).map_err(|e| tonic::Status::internal(e.to_string()))?;
        let mut client = self.client.clone();
        self.rt.block_on(client.localize(r)).map(|r| r.into_inner())
    }

    /// [`Remote::send`] of a query as raw RGB8 + float32 depth, as an evaluation answer.
    pub fn answer(
        &mut self,
        q: &Query,
        prior: Option<&Region>,
    ) -> Result<Answer, pntr_pipeline::PipelineError> {
        let req = proto::LocalizeRequest {
            prior: prior.map(wire::prior_message),
            // Evaluation compares with the dataset's poses, in the map's frame.
            frame_convention: proto::FrameConvention::Map as i32,
            ..wire::raw_request(&q.rgb, &q.depth, Some(&q.intrinsics))
        };
        let r = self
            .send(req)
            .map_err(|s| pntr_pipeline::PipelineError::Query(format!("server: {s}")))?;
        let axes = self.map_axes();
        let mut a = answer_of(&r);
        a.pose = a
            .pose
            .map(|p| pntr_core::convert_axes(&p, axes, pntr_core::CameraAxes::Habitat));
        Ok(a)
    }

    /// Camera axes of the answers of the map this client asks (GetMapInfo's `camera_axes`; Habitat's
    /// when the server does not say).
    pub fn map_axes(&mut self) -> pntr_core::CameraAxes {
        self.map_frames().camera
    }

    /// The frames of the map this client asks (GetMapInfo's `up_axis` and `camera_axes`; y up and
    /// Habitat's axes when the server does not say).
    pub fn map_frames(&mut self) -> wire::MapFrames {
        if let Some(f) = self.frames {
            return f;
        }
        let mut client = self.client.clone();
        let req = authorized(
            &self.connect,
            proto::GetMapInfoRequest {
                map_id: self.connect.map_id.clone(),
            },
        );
        let frames = req
            .ok()
            .and_then(|r| self.rt.block_on(client.get_map_info(r)).ok())
            .map(|info| wire::MapFrames::of_info(info.get_ref()))
            .unwrap_or_default();
        self.frames = Some(frames);
        frames
    }
}

/// `pntr info --addr`: what the server says of a map it serves (`GetMapInfo`), as text or JSON
/// (the message's fields, snake_case, proto3 JSON mapping aside: intrinsics as an object).
pub fn print_map_info(c: &ConnectArgs, json: bool) -> Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let info = rt.block_on(async {
        let mut client = client(channel(c).await?);
        let req = authorized(
            c,
            proto::GetMapInfoRequest {
                map_id: c.map_id.clone(),
            },
        )?;
        client.get_map_info(req).await.map_err(|s| {
            anyhow::anyhow!(
                "the server refused: {} ({})",
                s.message(),
                pntr_service::service::code_name(s.code())
            )
        })
    })?;
    let m = info.into_inner();
    let k = m.intrinsics.clone().unwrap_or_default();
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "map_id": m.map_id,
                "version": m.version,
                "built_at": m.built_at,
                "images": m.images,
                "points": m.points,
                "scenes": m.scenes,
                "preset": m.preset,
                "built_preset": m.built_preset,
                "extractor": m.extractor,
                "extractor_engine": m.extractor_engine,
                "matcher": m.matcher,
                "global_descriptor": m.global_descriptor,
                "camera_axes": m.camera_axes,
                "up_axis": m.up_axis,
                "frame_convention": wire::convention_name(m.frame_convention),
                "ros_from_map_wxyz": m.ros_from_map.as_ref().and_then(|p| p.rotation.as_ref()).map(|q| [q.w, q.x, q.y, q.z]),
                "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "distortion": k.distortion},
                "image_width": m.image_width,
                "image_height": m.image_height,
                "build_seconds": m.build_seconds,
                "loaded_map_ids": m.loaded_map_ids,
                "calibration": m.calibration.as_ref().map(calibration_json),
            }))?
        );
        return Ok(());
    }
    println!(
        "map {} version {} ({} images, {} places, scenes {})",
        m.map_id,
        m.version,
        m.images,
        m.points,
        m.scenes.join(", ")
    );
    println!(
        "preset {} (built with {}): {} on {} + {}, retrieval {}",
        m.preset, m.built_preset, m.extractor, m.extractor_engine, m.matcher, m.global_descriptor
    );
    println!(
        "answers in camera axes {} with the world's up axis {}; camera {}x{} fx {:.2} fy {:.2} cx {:.2} cy {:.2}",
        m.camera_axes, m.up_axis, m.image_width, m.image_height, k.fx, k.fy, k.cx, k.cy
    );
    println!(
        "answers by default in the {} convention (ask for `map` or `ros` per request; ROS: z-up map frame, optical camera axes)",
        wire::convention_name(m.frame_convention)
    );
    if let Some(c) = &m.calibration {
        match c.source.as_str() {
            "map" => println!(
                "calibration: the map's own{} (threshold {:.3}; {} regions held out, {} of {} own negatives LOCALIZED; expected precision {:.3})",
                if c.stale { ", STALE: the map changed since it was fitted" } else { "" },
                c.threshold,
                c.regions,
                c.false_positives,
                c.negatives,
                c.expected_precision
            ),
            other => println!("calibration: {other} (threshold {:.3})", c.threshold),
        }
    }
    println!("the server holds: {}", m.loaded_map_ids.join(", "));
    Ok(())
}

/// Server-reported stage times of a response, by name (queue included).
pub fn stage_seconds(r: &LocalizeResponse) -> Vec<(String, f64)> {
    r.timings
        .iter()
        .map(|t| (t.stage.clone(), t.seconds))
        .collect()
}

/// The evaluation view of a response.
pub fn answer_of(r: &LocalizeResponse) -> Answer {
    let mut times = StageTimes::default();
    for (stage, s) in stage_seconds(r) {
        match stage.as_str() {
            "extraction" => times.extraction = s,
            "retrieval" => times.retrieval = s,
            "matching" => times.matching = s,
            "registration" => times.registration = s,
            "verification" => times.verification = s,
            "resampling" => times.resampling = s,
            "total" => times.total = s,
            _ => {}
        }
    }
    let status = match proto::Status::try_from(r.status) {
        Ok(proto::Status::Localized) => Some(Status::Localized),
        Ok(proto::Status::NotLocalized) => Some(Status::NotLocalized),
        _ => None,
    };
    Answer {
        status,
        pose: if status == Some(Status::Localized) {
            wire::pose(r.pose.as_ref())
        } else {
            None
        },
        retrieved: r.retrieved_image_ids.clone(),
        matched: (!r.matched_image_id.is_empty()).then(|| r.matched_image_id.clone()),
        times,
        confidence: r.confidence,
        estimate: None,
        reason: (!r.reason.is_empty()).then(|| r.reason.clone()),
        threshold: Some(r.min_confidence),
        covariance: if status == Some(Status::Localized) {
            r.covariance.as_slice().try_into().ok()
        } else {
            None
        },
        mode: match proto::Mode::try_from(r.mode) {
            Ok(proto::Mode::Global) => Some(Mode::Global),
            Ok(proto::Mode::Prior) => Some(Mode::Prior),
            Ok(proto::Mode::Tracking) => Some(Mode::Tracking),
            _ => None,
        },
    }
}

/// A served map's calibration (`GetMapInfo.calibration`, `ListMaps`' `LoadedMap.calibration`) in
/// the JSON of `pntr info --addr --json` and `pntr maps list --json`.
pub(crate) fn calibration_json(c: &proto::CalibrationInfo) -> serde_json::Value {
    serde_json::json!({
        "source": c.source,
        "threshold": c.threshold,
        "fitted_on": c.fitted_on,
        "expected_precision": c.expected_precision,
        "negatives": c.negatives,
        "false_positives": c.false_positives,
        "regions": c.regions,
        "stale": c.stale,
    })
}
