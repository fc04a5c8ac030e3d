//! `alignist`: the command-line client of the gRPC service.

use std::path::PathBuf;
use std::time::Duration;

use alignist::client::{self, ClientError, ConnectOptions};
use alignist::serve::auth::Token;
use alignist::serve::proto::{DistributionRequest, PredictRequest};
use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};

/// Asks an alignist server how an object is oriented.
/// Writes a line to standard output; a closed or full stdout ends the command with a message
/// (exit 1), not a panic.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*).context("writing to standard output")?
    }};
}

/// Writes text (its own line ends included) to standard output, as [`out!`] does.
macro_rules! out_text {
    ($text:expr) => {{
        use std::io::Write as _;
        std::io::stdout()
            .lock()
            .write_all($text.as_bytes())
            .context("writing to standard output")?
    }};
}

#[derive(Parser)]
#[command(name = "alignist", version, about, long_about = None)]
struct Cli {
    /// Server URL.
    #[arg(
        long,
        global = true,
        env = "ALIGNIST_SERVER",
        default_value = "http://127.0.0.1:50051"
    )]
    server: String,
    /// Seconds before a call gives up (at least 1).
    #[arg(long, global = true, default_value_t = 60,
          value_parser = clap::value_parser!(u64).range(1..))]
    timeout_s: u64,
    /// For an https:// server: the PEM certificate to trust (its private CA, or the server's
    /// own self-signed certificate); without it, the public web roots.
    #[arg(long, global = true, env = "ALIGNIST_CA_FILE")]
    ca_file: Option<PathBuf>,
    /// A file holding the bearer token the server asks for (its --auth-token-file).
    #[arg(long, global = true, env = "ALIGNIST_TOKEN_FILE")]
    token_file: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Args)]
struct ImageArgs {
    /// Model name (empty: the server's only model).
    #[arg(long, default_value = "")]
    model: String,
    /// Object name (needed with several objects only for depth fusion).
    #[arg(long, default_value = "")]
    object: String,
    /// PNG or JPEG image of the object.
    #[arg(long)]
    image: PathBuf,
    /// Box of the object: x,y,width,height in pixels (fractions allowed; it may extend beyond
    /// the image).
    #[arg(long, value_parser = parse_crop)]
    crop: Option<[f64; 4]>,
}

#[derive(Subcommand)]
enum Command {
    /// Top-k rotations, MAP and modes for an image.
    Predict(PredictArgs),
    /// The full distribution at one grid level, written as CSV (index,probability,log_density).
    Distribution(DistributionArgs),
    /// The models the server holds.
    Models {
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// A bounded load test of Predict against a server on this machine (loopback only):
    /// prints requests/s, latency p50/p90/p99 and counts by status code; exits 1 on any failure.
    Load(LoadArgs),
    /// The server's health (grpc.health.v1); exits 1 unless SERVING.
    Health {
        /// Service name: by default the one that answers predictions (SERVING only once models
        /// are loaded); "" for the whole server (liveness: SERVING while models still load).
        #[arg(long, default_value = "alignist.v1.Alignist")]
        service: String,
    },
}

#[derive(Args)]
struct PredictArgs {
    #[command(flatten)]
    image: ImageArgs,
    /// How many rotations.
    #[arg(long, default_value_t = 10)]
    top_k: u32,
    /// Finest search level (0: the server's default).
    #[arg(long, default_value_t = 0)]
    level: u32,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
    /// Also draw the distribution at level 3 (IPDF-style plot) to this PNG.
    #[arg(long, conflicts_with = "intrinsics")]
    plot: Option<PathBuf>,
    /// The camera's intrinsics fx,fy,cx,cy in pixels: --image is then the full camera image,
    /// each --box is cropped as a virtual camera looking at it sees it, and every rotation is
    /// answered in the real camera's frame (PredictFrame).
    #[arg(long, value_parser = parse_intrinsics, requires = "boxes", conflicts_with = "crop")]
    intrinsics: Option<[f64; 4]>,
    /// A detection box x,y,width,height in pixels of the full image; repeat per object (needs
    /// --intrinsics).
    #[arg(long = "box", id = "boxes", value_parser = parse_crop, requires = "intrinsics")]
    boxes: Vec<[f64; 4]>,
    /// A depth image registered to --image (16-bit PNG; 0 = no measurement): RGB-D fusion,
    /// with each object's translation found (needs --intrinsics, --box, --depth-scale).
    #[arg(long, requires_all = ["intrinsics", "depth_scale"])]
    depth: Option<PathBuf>,
    /// Mesh units per depth unit (e.g. 0.001 for depth in mm and a mesh in metres).
    #[arg(long, requires = "depth")]
    depth_scale: Option<f64>,
    /// A mask PNG of the image's size (non-zero on the object), one per --box in order; only
    /// depth pixels inside it are used.
    #[arg(long = "mask", requires = "depth")]
    masks: Vec<PathBuf>,
    /// Depth points relative to the object's centre, in the camera frame and the mesh's
    /// units: a text file of "x y z" lines (the older input; for a crop, not --intrinsics).
    #[arg(long, conflicts_with_all = ["intrinsics", "depth"])]
    points: Option<PathBuf>,
}

#[derive(Args)]
struct DistributionArgs {
    #[command(flatten)]
    image: ImageArgs,
    /// Grid level.
    #[arg(long, default_value_t = 3)]
    level: u32,
    /// Output CSV.
    #[arg(long)]
    out: PathBuf,
    /// Also draw the distribution to this PNG.
    #[arg(long)]
    plot: Option<PathBuf>,
}

#[derive(Args)]
struct LoadArgs {
    /// Model name (empty: the server's only model).
    #[arg(long, default_value = "")]
    model: String,
    /// PNG or JPEG image sent with every call (default: a rendered cube at the model's size).
    #[arg(long)]
    image: Option<PathBuf>,
    /// Total calls.
    #[arg(long, default_value_t = 1000)]
    requests: usize,
    /// Calls in flight at once.
    #[arg(long, default_value_t = 8)]
    concurrency: usize,
    /// HTTP/2 connections the calls are spread over.
    #[arg(long, default_value_t = 4)]
    connections: usize,
    /// Top-k per call.
    #[arg(long, default_value_t = 5)]
    top_k: u32,
    /// Search level per call (0: the server's default).
    #[arg(long, default_value_t = 0)]
    level: u32,
}

fn parse_crop(s: &str) -> Result<[f64; 4], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("'{s}': {e} (expected x,y,width,height)"))?;
    let v: [f64; 4] = v
        .try_into()
        .map_err(|_| format!("'{s}': expected 4 numbers x,y,width,height"))?;
    if !(v.iter().all(|x| x.is_finite()) && v[2] > 0.0 && v[3] > 0.0) {
        return Err(format!(
            "'{s}': x and y must be finite, width and height positive (pixels; fractions and \
             boxes reaching beyond the image are fine)"
        ));
    }
    Ok(v)
}

fn parse_intrinsics(s: &str) -> Result<[f64; 4], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("'{s}': {e} (expected fx,fy,cx,cy)"))?;
    let v: [f64; 4] = v
        .try_into()
        .map_err(|_| format!("'{s}': expected 4 numbers fx,fy,cx,cy"))?;
    if !(v.iter().all(|x| x.is_finite()) && v[0] > 0.0 && v[1] > 0.0) {
        return Err(format!(
            "'{s}': fx and fy must be positive, all four finite"
        ));
    }
    Ok(v)
}

fn read_image(args: &ImageArgs) -> Result<alignist::serve::proto::ImageInput> {
    let data = std::fs::read(&args.image)
        .with_context(|| format!("reading --image {}", args.image.display()))?;
    Ok(client::image_input(data, args.crop))
}

/// Reads "x y z" lines (blank lines and `#` comments skipped) as depth points.
fn read_points(path: &PathBuf) -> Result<alignist::serve::proto::DepthPoints> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading --points {}", path.display()))?;
    let mut xyz = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let values: Vec<f32> = line
            .split(|c: char| c == ',' || c.is_whitespace())
            .filter(|s| !s.is_empty())
            .map(str::parse)
            .collect::<Result<_, _>>()
            .with_context(|| format!("--points {} line {}: '{line}'", path.display(), n + 1))?;
        if values.len() != 3 {
            bail!(
                "--points {} line {}: expected 3 numbers x y z, got {}",
                path.display(),
                n + 1,
                values.len()
            );
        }
        xyz.extend(values);
    }
    Ok(alignist::serve::proto::DepthPoints { xyz })
}

/// Draws a distribution of `level` (IPDF-style) to `path`.
fn save_plot(path: &PathBuf, level: u32, probs: &[f32]) -> Result<()> {
    let grid = alignist::so3::GridLevel::new(level as u8)?;
    let probs: Vec<f64> = probs.iter().map(|&p| p as f64).collect();
    alignist::viz::plot_distribution(&grid.quaternions(), &probs, &[], 1200)
        .save(path)
        .with_context(|| format!("writing --plot {}", path.display()))
}

/// A PNG of the cube at a fixed pose (64 × 64), for load runs without --image.
fn default_image() -> Result<Vec<u8>> {
    use alignist::cad::{Camera, RenderOptions, Shape, render};
    let r = alignist::so3::rot_z(0.4) * alignist::so3::rot_x(0.7);
    let rgb = render(
        &Shape::Cube.mesh(),
        &Camera::square(64),
        &alignist::data::symsol_pose(r),
        &RenderOptions::default(),
    )
    .rgb;
    let mut png = Vec::new();
    image::RgbImage::from_raw(64, 64, rgb)
        .context("render size")?
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    Ok(png)
}

async fn run(cli: Cli) -> Result<()> {
    let timeout = Duration::from_secs(cli.timeout_s);
    if matches!(cli.command, Command::Load { .. }) && !client::load::is_loopback(&cli.server) {
        bail!(
            "--server {}: the load generator only targets this machine (localhost, 127.0.0.1, ::1)",
            cli.server
        );
    }
    let token = match &cli.token_file {
        Some(path) => Some(Token::from_file(path).context("--token-file")?),
        None => None,
    };
    if token.is_some()
        && cli.server.starts_with("http://")
        && !client::load::is_loopback(&cli.server)
    {
        eprintln!(
            "warning: sending the token in plaintext to {}; use https://",
            cli.server
        );
    }
    let options = ConnectOptions {
        timeout,
        ca_file: cli.ca_file.clone(),
        token,
    };
    let channel = client::connect_with(&cli.server, &options).await?;
    match cli.command {
        Command::Predict(args) => match args.intrinsics {
            Some(intrinsics) => predict_frame(channel, &args, intrinsics).await,
            None => predict(channel, &args, &cli.server, &options).await,
        },
        Command::Distribution(args) => distribution(channel, &args).await,
        Command::Models { json } => models(channel, json).await,
        Command::Load(args) => load(channel, args, &cli.server, &options).await,
        Command::Health { service } => {
            let status = client::health(channel, &service).await?;
            out!("{status}");
            if status != "Serving" {
                bail!("server is {status}");
            }
            Ok(())
        }
    }
}

/// `predict --intrinsics … --box …`: PredictFrame, with depth and masks when given.
async fn predict_frame(
    channel: alignist::client::Connection,
    args: &PredictArgs,
    [fx, fy, cx, cy]: [f64; 4],
) -> Result<()> {
    use alignist::serve::proto::{DepthImage, Detection, FrameRequest, Intrinsics};
    if !args.masks.is_empty() && args.masks.len() != args.boxes.len() {
        bail!(
            "--mask: give one per --box ({} masks for {} boxes)",
            args.masks.len(),
            args.boxes.len()
        );
    }
    let masks: Vec<Vec<u8>> = args
        .masks
        .iter()
        .map(|m| std::fs::read(m).with_context(|| format!("reading --mask {}", m.display())))
        .collect::<Result<_>>()?;
    let depth = match &args.depth {
        None => None,
        Some(path) => Some(DepthImage {
            data: std::fs::read(path)
                .with_context(|| format!("reading --depth {}", path.display()))?,
            width: 0,
            height: 0,
            scale: args.depth_scale.unwrap_or_default(),
        }),
    };
    let detections = args
        .boxes
        .iter()
        .enumerate()
        .map(|(i, &b)| Detection {
            r#box: None,
            bbox: Some(alignist::client::pixel_box(b)),
            object: args.image.object.clone(),
            mask: masks.get(i).cloned().unwrap_or_default(),
        })
        .collect();
    let request = FrameRequest {
        model: args.image.model.clone(),
        image: Some(read_image(&args.image)?),
        intrinsics: Some(Intrinsics { fx, fy, cx, cy }),
        detections,
        top_k: args.top_k,
        level: args.level,
        mode_angle_deg: 0.0,
        depth,
    };
    let answer = client::predict_frame(channel, request).await?;
    if args.json {
        let json = serde_json::to_string_pretty(&client::frame_json(&answer))?;
        out!("{json}");
    } else {
        out_text!(client::frame_table(&answer));
    }
    Ok(())
}

/// `predict` of a crop: Predict, with centred depth points when given, and the level-3 plot.
async fn predict(
    channel: alignist::client::Connection,
    args: &PredictArgs,
    server: &str,
    options: &ConnectOptions,
) -> Result<()> {
    let depth = match &args.points {
        None => None,
        Some(path) => Some(read_points(path)?),
    };
    let request = PredictRequest {
        model: args.image.model.clone(),
        object: args.image.object.clone(),
        image: Some(read_image(&args.image)?),
        top_k: args.top_k,
        level: args.level,
        mode_angle_deg: 0.0,
        depth,
    };
    let answer = client::predict(channel, request).await?;
    if args.json {
        let json = serde_json::to_string_pretty(&client::predict_json(&answer))?;
        out!("{json}");
    } else {
        out_text!(client::predict_table(&answer));
    }
    if let Some(path) = &args.plot {
        // The plot shows the whole distribution (level 3), not just the top-k.
        let request = distribution_request(&args.image, 3)?;
        let channel = client::connect_with(server, options).await?;
        let (level, probs, _) = client::distribution(channel, request).await?;
        save_plot(path, level, &probs)?;
    }
    Ok(())
}

fn distribution_request(image: &ImageArgs, level: u32) -> Result<DistributionRequest> {
    Ok(DistributionRequest {
        model: image.model.clone(),
        object: image.object.clone(),
        image: Some(read_image(image)?),
        level,
        chunk_size: 0,
        depth: None,
    })
}

/// `distribution`: the CSV, and the plot when asked.
async fn distribution(
    channel: alignist::client::Connection,
    args: &DistributionArgs,
) -> Result<()> {
    let request = distribution_request(&args.image, args.level)?;
    let (level, probs, logs) = client::distribution(channel, request).await?;
    let mut csv = String::from("index,probability,log_density\n");
    for (i, (p, l)) in probs.iter().zip(&logs).enumerate() {
        csv.push_str(&format!("{i},{p:e},{l}\n"));
    }
    std::fs::write(&args.out, csv)
        .with_context(|| format!("writing --out {}", args.out.display()))?;
    let total: f64 = probs.iter().map(|&p| p as f64).sum();
    out!(
        "level {level}: {} cells, total probability {total:.6}, written to {}",
        probs.len(),
        args.out.display()
    );
    if let Some(path) = &args.plot {
        save_plot(path, level, &probs)?;
    }
    Ok(())
}

/// `models`: the table, or JSON.
async fn models(channel: alignist::client::Connection, json: bool) -> Result<()> {
    let list = client::models(channel).await?;
    if !json {
        out_text!(client::models_table(&list));
        return Ok(());
    }
    let models: Vec<serde_json::Value> = list
        .models
        .iter()
        .map(|m| {
            serde_json::json!({
                "name": m.name, "input_size": m.input_size,
                "full_max_level": m.full_max_level,
                "search_max_level": m.search_max_level,
                "objects": m.objects.iter().map(|o| &o.name).collect::<Vec<_>>(),
            })
        })
        .collect();
    let failed: Vec<serde_json::Value> = list
        .failed
        .iter()
        .map(|f| {
            serde_json::json!({
                "name": f.name, "error": f.error,
                "serving_previous": f.serving_previous,
            })
        })
        .collect();
    let json = serde_json::json!({ "models": models, "failed": failed });
    out!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// `load`: the bounded load test over `--connections` channels.
async fn load(
    channel: alignist::client::Connection,
    args: LoadArgs,
    server: &str,
    options: &ConnectOptions,
) -> Result<()> {
    if args.requests == 0 || args.concurrency == 0 || args.connections == 0 {
        bail!("--requests, --concurrency and --connections must be at least 1");
    }
    let data = match &args.image {
        Some(path) => {
            std::fs::read(path).with_context(|| format!("reading --image {}", path.display()))?
        }
        None => default_image()?,
    };
    let mut channels = vec![channel];
    for _ in 1..args.connections {
        channels.push(client::connect_with(server, options).await?);
    }
    let request = PredictRequest {
        model: args.model,
        image: Some(client::image_input(data, None)),
        top_k: args.top_k,
        level: args.level,
        ..Default::default()
    };
    let report = client::load::run_load(
        channels,
        request,
        args.requests,
        args.concurrency,
        options.timeout,
    )
    .await?;
    out!("{report}");
    if report.failures() > 0 {
        bail!("{} of {} calls failed", report.failures(), report.requests);
    }
    Ok(())
}

fn main() {
    let cli = Cli::parse();
    let runtime = tokio::runtime::Runtime::new().expect("async runtime");
    if let Err(e) = runtime.block_on(run(cli)) {
        match e.downcast_ref::<ClientError>() {
            Some(ClientError::Status { .. }) | Some(ClientError::Connect { .. }) => {
                eprintln!("error: {e}")
            }
            None => eprintln!("error: {e:#}"),
        }
        std::process::exit(1);
    }
}
