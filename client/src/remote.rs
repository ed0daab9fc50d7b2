//! Localising through a running `pntr-server`: the client side of `pntr eval --remote` and `pntr demo`.

use std::time::Duration;

use anyhow::{Context, Result};
use pntr_pipeline::eval::Answer;
use pntr_pipeline::pipeline::{Query, StageTimes, Status};
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::{self, LocalizeResponse};
use pntr_service::tonic::transport::Channel;
use pntr_service::{tokio, tonic, wire};

/// A blocking client over a small Tokio runtime of its own.
pub struct Remote {
    rt: tokio::runtime::Runtime,
    client: LocalizerClient<Channel>,
    /// Map id sent with every request (empty = the server's only map).
    pub map_id: String,
}

impl Remote {
    /// Connect to `addr` (`host:port` or a URL).
    pub fn connect(addr: &str, map_id: &str) -> Result<Self> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let url = if addr.contains("://") {
            addr.to_string()
        } else {
            format!("http://{addr}")
        };
        let channel = rt
            .block_on(
                tonic::transport::Endpoint::from_shared(url.clone())?
                    .connect_timeout(Duration::from_secs(10))
                    .connect(),
            )
            .with_context(|| format!("connecting to pntr-server at {url}"))?;
        let client = LocalizerClient::new(channel)
            .max_decoding_message_size(64 << 20)
            .max_encoding_message_size(64 << 20);
        Ok(Self {
            rt,
            client,
            map_id: map_id.to_string(),
        })
    }

    /// Send one frame (raw RGB8 + float32 depth) and wait for the answer.
    pub fn localize(&mut self, q: &Query) -> Result<LocalizeResponse, tonic::Status> {
        let mut req = wire::raw_request(&q.rgb, &q.depth, Some(&q.intrinsics));
        req.map_id = self.map_id.clone();
        let mut client = self.client.clone();
        self.rt
            .block_on(client.localize(req))
            .map(|r| r.into_inner())
    }

    /// [`Remote::localize`] as an evaluation answer.
    pub fn answer(&mut self, q: &Query) -> Result<Answer, pntr_pipeline::PipelineError> {
        let r = self
            .localize(q)
            .map_err(|s| pntr_pipeline::PipelineError::Query(format!("server: {s}")))?;
        Ok(answer_of(&r))
    }
}

/// The evaluation view of a response.
pub fn answer_of(r: &LocalizeResponse) -> Answer {
    let mut times = StageTimes::default();
    for t in &r.timings {
        match t.stage.as_str() {
            "extraction" => times.extraction = t.seconds,
            "retrieval" => times.retrieval = t.seconds,
            "matching" => times.matching = t.seconds,
            "registration" => times.registration = t.seconds,
            "total" => times.total = t.seconds,
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
    }
}
