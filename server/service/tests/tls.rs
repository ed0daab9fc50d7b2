//! TLS (rustls) with a certificate chain generated here: a TLS client that trusts the CA is served,
//! a plaintext client is not, and the bearer token is still required inside TLS.

mod common;

use pntr_service::config::Settings;
use pntr_service::proto::localizer_client::LocalizerClient;
use pntr_service::proto::GetMapInfoRequest;
use pntr_service::tonic::transport::{Certificate, ClientTlsConfig, Endpoint};
use pntr_service::tonic::{Code, Request};
use pntr_service::tonic_health::pb::health_client::HealthClient;
use pntr_service::tonic_health::pb::HealthCheckRequest;
use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair};

#[test]
fn tls_with_token() {
    let dir = tempfile::tempdir().unwrap();
    let (db, _) = common::demo_map(dir.path());
    // A CA, and a server certificate for localhost signed by it.
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca_key = KeyPair::generate().unwrap();
    let ca_cert = ca_params.self_signed(&ca_key).unwrap();
    let issuer = Issuer::new(ca_params, ca_key);
    let leaf_key = KeyPair::generate().unwrap();
    let leaf = CertificateParams::new(vec!["localhost".to_string()])
        .unwrap()
        .signed_by(&leaf_key, &issuer)
        .unwrap();
    let (cert, key) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
    std::fs::write(&cert, leaf.pem()).unwrap();
    std::fs::write(&key, leaf_key.serialize_pem()).unwrap();

    let mut s = Settings::local(vec![db], common::models());
    s.workers = 1;
    s.tls = Some((cert, key));
    s.token = Some("tls-token".into());
    let rt = common::runtime();
    rt.block_on(async {
        let mut running = pntr_service::start(s).await.unwrap();
        running.ready().await.unwrap();
        let port = running.addr.port();
        let tls = ClientTlsConfig::new()
            .ca_certificate(Certificate::from_pem(ca_cert.pem()))
            .domain_name("localhost");
        let channel = Endpoint::from_shared(format!("https://127.0.0.1:{port}"))
            .unwrap()
            .tls_config(tls)
            .unwrap()
            .connect()
            .await
            .unwrap();
        let status = HealthClient::new(channel.clone())
            .check(HealthCheckRequest::default())
            .await
            .unwrap()
            .into_inner()
            .status;
        assert_eq!(status, 1, "SERVING");
        let mut c = LocalizerClient::new(channel);
        let e = c
            .get_map_info(GetMapInfoRequest::default())
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::Unauthenticated);
        let mut req = Request::new(GetMapInfoRequest::default());
        req.metadata_mut()
            .insert("authorization", "Bearer tls-token".parse().unwrap());
        let info = c.get_map_info(req).await.unwrap().into_inner();
        assert_eq!(info.map_id, "demo");

        // Plaintext HTTP/2 to a TLS port gets nowhere.
        let plain = Endpoint::from_shared(format!("http://127.0.0.1:{port}"))
            .unwrap()
            .connect()
            .await;
        if let Ok(ch) = plain {
            assert!(HealthClient::new(ch)
                .check(HealthCheckRequest::default())
                .await
                .is_err());
        }
        running.shutdown();
        running.wait().await.unwrap();
    });
}
