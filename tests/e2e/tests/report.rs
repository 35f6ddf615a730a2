//! The deadline rush's HTML report as a person opens it: in headless Chromium (Debian's), every
//! chart drawn with no script error, and a screenshot that is not blank.

use std::path::Path;
use std::process::Command;

use e2e::report::{self, Chart, EvalAiRush};
use lb_domain::capacity::cost::InstancePrice;
use lb_domain::capacity::fleet::{self, Mode, Model, Rush, Shape};

/// Headless Chromium on `page` with `args`, through the script `make bench-scale` uses too
/// (its flags are this machine's needs).
fn headless(page: &Path, args: &[&str]) -> std::process::Output {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/headless.sh");
    Command::new("bash")
        .arg(script)
        .args(args)
        .arg(page)
        .output()
        .expect("bash runs")
}

/// The page's DOM once its script ran.
fn dom(page: &Path) -> String {
    let out = headless(page, &["--dump-dom"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// An attribute of the body, as the script left it.
fn body_attribute(dom: &str, name: &str) -> Option<String> {
    let body = &dom[dom.find("<body")?..];
    let body = &body[..body.find('>')?];
    let at = body.find(&format!("{name}=\""))? + name.len() + 2;
    Some(body[at..at + body[at..].find('"')?].to_owned())
}

/// A small rush on the fleet model, the runs the report draws, and a made-up EvalAI log.
fn charts() -> Vec<Chart> {
    let price = InstancePrice {
        on_demand: 5.672,
        spot: 2.27,
    };
    let shape = Shape {
        submissions: 16,
        teams: 4,
        hours: 1.0,
        routes: 8,
        pairs: 4,
        scale: 1.0,
        team_limit: 2,
    };
    let rush = Rush::deadline(shape, 7);
    let before = Model::eks_g5(price, 4);
    let runs: Vec<(String, fleet::Report)> = [
        ("original", &before, Mode::Original),
        ("on-demand, as deployed", &before, Mode::OnDemand),
        ("spot-first, levers", &before.with_levers(), Mode::SpotFirst),
    ]
    .into_iter()
    .map(|(name, model, mode)| (name.to_owned(), fleet::simulate(model, mode, &rush)))
    .collect();
    let mut charts = report::fleet_charts(&runs);
    // Two requests a second for a minute, then one a second.
    let requests_ms: Vec<i128> = (0..120)
        .map(|i| i * 500)
        .chain((60..120).map(|i| i * 1000))
        .collect();
    let seen = EvalAiRush {
        name: "on-demand".into(),
        requests_ms,
        admission: vec![0.0, 1.0, 4.0, 9.0],
        start: vec![1.0, 2.0, 6.0, 12.0],
    };
    charts.extend(report::evalai_charts(&[seen], 60_000, 1.0, 60));
    charts
}

#[test]
#[ignore = "needs Chromium (make test installs it)"]
fn the_rush_report_draws_every_chart_in_chromium_and_its_screenshot_is_not_blank() {
    let dir = tempfile::tempdir().unwrap();
    let charts = charts();
    assert_eq!(
        charts.len(),
        8,
        "queue, two fleets, waits, estimates, cost, EvalAI, admission"
    );
    let page = dir.path().join("report.html");
    std::fs::write(&page, report::page("The rush", "the bench's text", &charts)).unwrap();
    let dom = dom(&page);
    assert_eq!(
        body_attribute(&dom, "data-errors").as_deref(),
        Some(""),
        "script errors"
    );
    assert_eq!(
        body_attribute(&dom, "data-charts-drawn"),
        Some(charts.len().to_string())
    );
    assert_eq!(dom.matches("data-drawn=\"true\"").count(), charts.len());
    // Each chart drew its series: a line or bar for every one.
    for chart in &charts {
        let start = dom.find(&format!("id=\"{}\"", chart.id)).unwrap();
        let end = dom[start..].find("</svg>").unwrap() + start;
        let drawn = dom[start..end].matches("class=\"series\"").count();
        let expected = match chart.kind {
            report::Kind::Line => chart.series.iter().filter(|s| !s.points.is_empty()).count(),
            report::Kind::Bars => chart.labels.len(),
        };
        assert!(
            expected > 0 && drawn == expected,
            "{}: {drawn} of {expected}",
            chart.id
        );
    }
    assert_eq!(
        dom.matches("class=\"limit\"").count(),
        1,
        "EvalAI's limit drawn"
    );

    // The screenshot: the page as a person sees it, not blank (charts in colour on white).
    let shot = dir.path().join("report.png");
    let out = headless(
        &page,
        &[
            "--window-size=1240,2200",
            &format!("--screenshot={}", shot.display()),
        ],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&shot).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut pixels).unwrap();
    let channels = info.color_type.samples();
    let colours: std::collections::BTreeSet<&[u8]> = pixels[..info.buffer_size()]
        .chunks(channels)
        .filter(|px| px[..3].iter().any(|&c| c < 200))
        .collect();
    assert!(
        colours.len() > 20,
        "{} colours off white: blank?",
        colours.len()
    );

    // The checks see a chart that cannot be drawn.
    let mut broken = charts.clone();
    broken[0].series.clear();
    std::fs::write(&page, report::page("The rush", "", &broken)).unwrap();
    let dom = self::dom(&page);
    assert!(
        body_attribute(&dom, "data-errors").is_some_and(|e| e.contains("queue: no points")),
        "{dom}"
    );
    assert_eq!(
        body_attribute(&dom, "data-charts-drawn"),
        Some((charts.len() - 1).to_string())
    );
}
