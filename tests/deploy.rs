//! Consistency of the deployment files: the grace period covers preStop + drain, the image runs
//! as a non-root user with a health check through the client, and ports agree.

fn read(path: &str) -> String {
    std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(path))
        .unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn number_after(text: &str, key: &str) -> u64 {
    let at = text.find(key).unwrap_or_else(|| panic!("{key} not found"));
    text[at + key.len()..]
        .trim_start_matches([' ', ':', '"', '='])
        .chars()
        .take_while(|c| c.is_ascii_digit())
        .collect::<String>()
        .parse()
        .unwrap_or_else(|_| panic!("{key} has no number"))
}

#[test]
fn kubernetes_grace_period_covers_pre_stop_and_drain() {
    let d = read("deploy/k8s/deployment.yaml");
    let grace = number_after(&d, "terminationGracePeriodSeconds");
    let pre_stop = number_after(&d, "seconds");
    let drain_at = d.find("ALIGNIST_DRAIN_TIMEOUT_S").unwrap();
    let drain = number_after(&d[drain_at..], "value");
    assert!(grace > pre_stop + drain, "{grace} ≤ {pre_stop} + {drain}");
    for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
        let at = d.find(probe).unwrap();
        assert!(
            d[at..]
                .trim_start_matches(|c| c != '\n')
                .trim_start()
                .starts_with("grpc:")
        );
    }
    assert!(read("deploy/k8s/service.yaml").contains("clusterIP: None"));
    for f in ["hpa.yaml", "pdb.yaml", "service.yaml", "deployment.yaml"] {
        assert!(read("deploy/k8s/kustomization.yaml").contains(f), "{f}");
    }
}

#[test]
fn image_is_non_root_checks_health_and_exposes_the_configured_ports() {
    let f = read("deploy/Dockerfile");
    assert!(f.contains("USER alignist"));
    assert!(f.contains("HEALTHCHECK") && f.contains("\"health\""));
    assert!(f.contains("ALIGNIST_LISTEN=0.0.0.0:50051") && f.contains("EXPOSE 50051 9469"));
    assert!(f.contains("ALIGNIST_METRICS_LISTEN=0.0.0.0:9469"));
    assert!(f.contains("COPY --chown=alignist models"));
    let compose = read("deploy/docker-compose.yml");
    let grace = number_after(&compose, "stop_grace_period");
    let drain = number_after(&compose, "ALIGNIST_DRAIN_TIMEOUT_S");
    assert!(grace > drain);
    assert!(read("deploy/prometheus.yml").contains("alignist:9469"));
}

/// The `key: value` pairs of the first `field:` block after `anchor` in a YAML text, read by
/// indentation (enough for these files; no YAML library is a dependency).
fn block_pairs(text: &str, anchor: &str, field: &str) -> Vec<(String, String)> {
    let from = text
        .find(anchor)
        .unwrap_or_else(|| panic!("{anchor} not found"));
    let mut lines = text[from..]
        .lines()
        .skip_while(|l| l.trim().trim_start_matches("- ") != format!("{field}:"));
    let head = lines
        .next()
        .unwrap_or_else(|| panic!("no {field}: after {anchor}"));
    // The column of the field's name (after a list item's "- ").
    let indent = head.find(field).expect("the field is on its line");
    lines
        .take_while(|l| l.trim().is_empty() || l.len() - l.trim_start().len() > indent)
        .filter(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .filter_map(|l| {
            let (k, v) = l.trim().split_once(':')?;
            Some((k.trim().to_string(), v.trim().trim_matches('"').to_string()))
        })
        .filter(|(_, v)| !v.is_empty())
        .collect()
}

#[test]
fn the_disruption_budget_selects_the_deployments_pods_as_kustomize_renders_them() {
    // What `kubectl kustomize deploy/k8s` does with these files: the kustomization's labels
    // (with includeSelectors) join the pod template's labels and every existing selector.
    let kustomization = read("deploy/k8s/kustomization.yaml");
    assert!(kustomization.contains("includeSelectors: true"));
    let common = block_pairs(&kustomization, "labels:", "pairs");
    assert!(!common.is_empty());
    let deployment = read("deploy/k8s/deployment.yaml");
    let mut pod_labels = block_pairs(&deployment, "template:", "labels");
    pod_labels.extend(common.iter().cloned());
    let pdb = read("deploy/k8s/pdb.yaml");
    let mut selector = block_pairs(&pdb, "selector:", "matchLabels");
    assert!(
        !selector.is_empty(),
        "a PDB without a selector protects no pod"
    );
    selector.extend(common.iter().cloned());
    for pair in &selector {
        assert!(
            pod_labels.contains(pair),
            "the PDB selects {pair:?}, which the pods {pod_labels:?} do not carry"
        );
    }
    // Clients behind the headless Service reconnect to new pods: connections have a maximum age.
    assert!(deployment.contains("ALIGNIST_MAX_CONNECTION_AGE_S"));
    // Liveness asks the whole server, readiness the service (SERVING once models are loaded).
    let readiness = &deployment[deployment.find("readinessProbe").unwrap()..];
    assert!(readiness[..200].contains("service: alignist.v1.Alignist"));
}

#[test]
fn deployments_serve_tls_with_a_token_and_probe_the_plaintext_health_port() {
    let d = read("deploy/k8s/deployment.yaml");
    for key in [
        "ALIGNIST_TLS_CERT",
        "ALIGNIST_TLS_KEY",
        "ALIGNIST_AUTH_TOKEN_FILE",
        "secretName: alignist-tls",
        "secretName: alignist-token",
        "fsGroup: 10001",
    ] {
        assert!(d.contains(key), "deployment.yaml lacks {key}");
    }
    // Every probe asks the port the health-only listener binds.
    let at = d.find("ALIGNIST_HEALTH_LISTEN").unwrap();
    let health_port = number_after(&d[at..], "value: \"0.0.0.0:");
    for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
        let at = d.find(probe).unwrap();
        assert_eq!(number_after(&d[at..], "port"), health_port, "{probe}");
    }
    let f = read("deploy/Dockerfile");
    let at = f.find("ALIGNIST_HEALTH_LISTEN").unwrap();
    let port = number_after(&f[at..], "=127.0.0.1:");
    assert!(f.contains(&format!("\"http://127.0.0.1:{port}\"")));
    let compose = read("deploy/docker-compose.yml");
    for key in [
        "ALIGNIST_TLS_CERT: /run/secrets/tls_cert",
        "ALIGNIST_TLS_KEY: /run/secrets/tls_key",
        "ALIGNIST_AUTH_TOKEN_FILE: /run/secrets/auth_token",
        "file: ./secrets/server.pem",
    ] {
        assert!(compose.contains(key), "docker-compose.yml lacks {key}");
    }
    assert!(read("deploy/make-secrets.sh").contains("deploy/secrets"));
}
