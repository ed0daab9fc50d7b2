//! The link to pntr-server: one `LocalizeStream` carrying the node's frames in order (so the
//! server tracks the robot between them), reopened with back-off when the server goes away
//! (UNAVAILABLE on shutdown, a refused connection while it restarts).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};

use crate::proto;
use crate::proto::localizer_client::LocalizerClient;

/// How to reach the server.
#[derive(Clone, Debug)]
pub struct Target {
    /// HOST:PORT.
    pub addr: String,
    /// Bearer token (`authorization: Bearer <token>`), if the server wants one.
    pub token: Option<String>,
    /// CA certificate (PEM) to verify a TLS server with.
    pub tls_ca: Option<PathBuf>,
    /// The name the server's certificate holds, when not the host of `addr`.
    pub tls_domain: Option<String>,
    /// Time one frame may take before the stream is given up and reopened.
    pub answer_timeout: Duration,
}

/// An open `LocalizeStream`.
struct Open {
    requests: mpsc::Sender<proto::LocalizeRequest>,
    answers: tonic::Streaming<proto::LocalizeResponse>,
}

/// The stream and its reconnection state.
pub struct Link {
    target: Target,
    open: Option<Open>,
    /// Earliest next attempt to connect.
    retry_at: Instant,
    backoff: Duration,
    /// The last failure, for diagnostics.
    pub last_error: Option<String>,
    /// Streams opened so far (1 = never reconnected).
    pub connections: u64,
}

const MIN_BACKOFF: Duration = Duration::from_millis(250);
const MAX_BACKOFF: Duration = Duration::from_secs(5);

impl Link {
    /// A link that connects on its first frame.
    pub fn new(target: Target) -> Self {
        Self {
            target,
            open: None,
            retry_at: Instant::now(),
            backoff: MIN_BACKOFF,
            last_error: None,
            connections: 0,
        }
    }

    /// Whether a stream is open.
    pub fn is_open(&self) -> bool {
        self.open.is_some()
    }

    async fn connect(&self) -> Result<Open> {
        let t = &self.target;
        let scheme = if t.tls_ca.is_some() { "https" } else { "http" };
        let mut ep = Endpoint::from_shared(format!("{scheme}://{}", t.addr))
            .with_context(|| format!("--addr {}: not HOST:PORT", t.addr))?
            .connect_timeout(Duration::from_secs(3))
            .tcp_nodelay(true);
        if let Some(ca) = &t.tls_ca {
            let pem = std::fs::read(ca)
                .with_context(|| format!("--tls-ca {}: cannot read it", ca.display()))?;
            let host = t.addr.rsplit_once(':').map_or(t.addr.as_str(), |(h, _)| h);
            let tls = ClientTlsConfig::new()
                .ca_certificate(Certificate::from_pem(pem))
                .domain_name(t.tls_domain.clone().unwrap_or_else(|| host.to_string()));
            ep = ep.tls_config(tls).context("TLS configuration")?;
        }
        let channel: Channel = ep
            .connect()
            .await
            .with_context(|| format!("cannot connect to {}", t.addr))?;
        let mut client = LocalizerClient::new(channel)
            .max_decoding_message_size(64 << 20)
            .max_encoding_message_size(64 << 20);
        let (requests, rx) = mpsc::channel(4);
        let mut request = tonic::Request::new(ReceiverStream::new(rx));
        if let Some(token) = &t.token {
            let value = format!("Bearer {token}")
                .parse()
                .context("--token: not a valid header value")?;
            request.metadata_mut().insert("authorization", value);
        }
        let answers = client
            .localize_stream(request)
            .await
            .map_err(|s| anyhow::anyhow!("LocalizeStream: {}: {}", s.code(), s.message()))?
            .into_inner();
        Ok(Open { requests, answers })
    }

    /// Localize one frame: its answer, or why there is none (no server, the stream broke). A
    /// broken stream is dropped and reopened for a later frame after a back-off of 0.25-5 s.
    pub async fn localize(
        &mut self,
        request: proto::LocalizeRequest,
    ) -> Result<proto::LocalizeResponse, String> {
        if self.open.is_none() {
            if Instant::now() < self.retry_at {
                return Err(self
                    .last_error
                    .clone()
                    .unwrap_or_else(|| "not connected".into()));
            }
            match self.connect().await {
                Ok(o) => {
                    self.open = Some(o);
                    self.connections += 1;
                    tracing::info!(addr = %self.target.addr, "LocalizeStream open");
                }
                Err(e) => return Err(self.failed(format!("{e:#}"))),
            }
        }
        let open = self.open.as_mut().expect("opened above");
        if open.requests.send(request).await.is_err() {
            return Err(self.failed("the stream was closed by the server".into()));
        }
        match tokio::time::timeout(self.target.answer_timeout, open.answers.message()).await {
            Ok(Ok(Some(answer))) => {
                self.backoff = MIN_BACKOFF;
                self.last_error = None;
                Ok(answer)
            }
            Ok(Ok(None)) => Err(self.failed("the server ended the stream".into())),
            Ok(Err(s)) => Err(self.failed(format!("{}: {}", s.code(), s.message()))),
            Err(_) => Err(self.failed(format!(
                "no answer within {:.1} s",
                self.target.answer_timeout.as_secs_f64()
            ))),
        }
    }

    fn failed(&mut self, why: String) -> String {
        tracing::warn!(addr = %self.target.addr, "pntr-server: {why}; reconnecting in {:.2} s", self.backoff.as_secs_f64());
        self.open = None;
        self.retry_at = Instant::now() + self.backoff;
        self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
        self.last_error = Some(why.clone());
        why
    }
}
