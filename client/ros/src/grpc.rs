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
    /// Whether the last failure was the server refusing (a missing map, a wrong token) rather than
    /// the server being away.
    pub refused: bool,
    /// Streams opened so far (1 = never reconnected).
    pub connections: u64,
    endpoint: Endpoint,
}

/// The endpoint of `target`: its address parsed, its TLS files read.
fn endpoint(t: &Target) -> Result<Endpoint> {
    let scheme = if t.tls_ca.is_some() { "https" } else { "http" };
    let uri = format!("{scheme}://{}", t.addr);
    let parsed: tonic::codegen::http::Uri = uri
        .parse()
        .ok()
        .filter(|u: &tonic::codegen::http::Uri| u.port_u16().is_some())
        .with_context(|| format!("--addr {}: not HOST:PORT", t.addr))?;
    let mut ep = Endpoint::from(parsed)
        .connect_timeout(Duration::from_secs(3))
        .tcp_nodelay(true);
    if let Some(ca) = &t.tls_ca {
        let pem = std::fs::read(ca)
            .with_context(|| format!("--tls-ca {}: cannot read it", ca.display()))?;
        let host = t.addr.rsplit_once(':').map_or(t.addr.as_str(), |(h, _)| h);
        let tls = ClientTlsConfig::new()
            .ca_certificate(Certificate::from_pem(pem))
            .domain_name(t.tls_domain.clone().unwrap_or_else(|| host.to_string()));
        ep = ep.tls_config(tls).context("--tls-ca: TLS configuration")?;
    }
    Ok(ep)
}

/// The innermost error of a chain (transport errors repeat their outer layers' text).
fn root_cause(e: &(dyn std::error::Error + 'static)) -> String {
    let mut inner = e;
    while let Some(next) = inner.source() {
        inner = next;
    }
    inner.to_string()
}

/// A gRPC status in words, with the likely mistake for the codes a node's configuration causes.
fn describe(s: &tonic::Status) -> String {
    let hint = match s.code() {
        tonic::Code::NotFound => " (--map-id names a map the server does not hold)",
        tonic::Code::Unauthenticated => " (--token is missing or wrong)",
        tonic::Code::Unimplemented => " (--addr is not a pntr-server's gRPC port)",
        _ => "",
    };
    format!("{:?}: {}{hint}", s.code(), s.message())
}

/// Codes that retrying soon will not change.
fn is_refusal(code: tonic::Code) -> bool {
    matches!(
        code,
        tonic::Code::NotFound
            | tonic::Code::Unauthenticated
            | tonic::Code::PermissionDenied
            | tonic::Code::Unimplemented
            | tonic::Code::InvalidArgument
    )
}

const MIN_BACKOFF: Duration = Duration::from_millis(250);
const MAX_BACKOFF: Duration = Duration::from_secs(5);

impl Link {
    /// A link that connects on its first frame. The address and the TLS files are checked here,
    /// so a mistake in them stops the node at start rather than at the first frame.
    pub fn new(target: Target) -> Result<Self> {
        let endpoint = endpoint(&target)?;
        Ok(Self {
            target,
            endpoint,
            open: None,
            retry_at: Instant::now(),
            backoff: MIN_BACKOFF,
            last_error: None,
            refused: false,
            connections: 0,
        })
    }

    /// Whether a stream is open.
    pub fn is_open(&self) -> bool {
        self.open.is_some()
    }

    async fn connect(&self) -> Result<Open> {
        let t = &self.target;
        let channel: Channel = self
            .endpoint
            .connect()
            .await
            .map_err(|e| anyhow::anyhow!("cannot connect to {}: {}", t.addr, root_cause(&e)))?;
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
            .map_err(|s| anyhow::Error::new(s.clone()).context(describe(&s)))?
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
            match tokio::time::timeout(self.target.answer_timeout, self.connect()).await {
                Ok(Ok(o)) => {
                    self.open = Some(o);
                    self.connections += 1;
                    tracing::info!(addr = %self.target.addr, "LocalizeStream open");
                }
                Ok(Err(e)) => {
                    let code = e.downcast_ref::<tonic::Status>().map(|s| s.code());
                    return Err(self.failed(format!("{e:#}"), code));
                }
                Err(_) => {
                    return Err(self.failed(
                        format!(
                            "{} accepted the connection but opened no stream within {:.1} s (is it a pntr-server?)",
                            self.target.addr,
                            self.target.answer_timeout.as_secs_f64()
                        ),
                        None,
                    ))
                }
            }
        }
        let open = self.open.as_mut().expect("opened above");
        if open.requests.send(request).await.is_err() {
            return Err(self.failed("the stream was closed by the server".into(), None));
        }
        match tokio::time::timeout(self.target.answer_timeout, open.answers.message()).await {
            Ok(Ok(Some(answer))) => {
                self.backoff = MIN_BACKOFF;
                self.last_error = None;
                self.refused = false;
                Ok(answer)
            }
            Ok(Ok(None)) => Err(self.failed("the server ended the stream".into(), None)),
            Ok(Err(s)) => Err(self.failed(describe(&s), Some(s.code()))),
            Err(_) => Err(self.failed(
                format!(
                    "no answer within {:.1} s",
                    self.target.answer_timeout.as_secs_f64()
                ),
                None,
            )),
        }
    }

    fn failed(&mut self, why: String, code: Option<tonic::Code>) -> String {
        self.refused = code.is_some_and(is_refusal);
        if self.refused {
            // The same answer again in a moment helps no one: wait the longest back-off.
            self.backoff = MAX_BACKOFF;
        }
        tracing::warn!(addr = %self.target.addr, "pntr-server: {why}; trying again in {:.2} s", self.backoff.as_secs_f64());
        self.open = None;
        self.retry_at = Instant::now() + self.backoff;
        self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
        self.last_error = Some(why.clone());
        why
    }
}
