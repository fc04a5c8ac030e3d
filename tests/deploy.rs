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
    assert!(f.contains("ALIGNIST_LISTEN=0.0.0.0:50051") && f.contains("EXPOSE 50051 9100"));
    assert!(f.contains("ALIGNIST_METRICS_LISTEN=0.0.0.0:9100"));
    assert!(f.contains("COPY --chown=alignist models"));
    let compose = read("deploy/docker-compose.yml");
    let grace = number_after(&compose, "stop_grace_period");
    let drain = number_after(&compose, "ALIGNIST_DRAIN_TIMEOUT_S");
    assert!(grace > drain);
    assert!(read("deploy/prometheus.yml").contains("alignist:9100"));
}
