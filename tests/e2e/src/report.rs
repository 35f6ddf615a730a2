//! The deadline rush's HTML report (`make bench-scale`): its charts as data, and one
//! self-contained page (no file or network beside it) whose script draws each as SVG.

use lb_domain::capacity::fleet::{Moment, Report};
use serde::Serialize;

/// How a chart draws its series.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// Lines over a numeric x.
    Line,
    /// One bar per label (a single series, its points' y in the labels' order).
    Bars,
}

/// One line (or the bars) of a chart.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Series {
    /// Its legend.
    pub name: String,
    /// (x, y).
    pub points: Vec<(f64, f64)>,
}

/// A horizontal line a chart holds its series against.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Limit {
    /// What it is.
    pub label: String,
    /// Its y.
    pub value: f64,
}

/// One chart.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Chart {
    /// Its element's id.
    pub id: String,
    /// Its title.
    pub title: String,
    /// A sentence under it: what to read in it.
    pub note: String,
    /// Lines or bars.
    pub kind: Kind,
    /// The x axis' label.
    pub x: String,
    /// The y axis' label.
    pub y: String,
    /// Its series.
    pub series: Vec<Series>,
    /// The bars' labels.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub labels: Vec<String>,
    /// A limit drawn across.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub limit: Option<Limit>,
}

impl Chart {
    fn line(id: &str, title: &str, (x, y): (&str, &str), series: Vec<Series>) -> Chart {
        Chart {
            id: id.into(),
            title: title.into(),
            note: String::new(),
            kind: Kind::Line,
            x: x.into(),
            y: y.into(),
            series,
            labels: Vec::new(),
            limit: None,
        }
    }

    fn noting(mut self, note: &str) -> Chart {
        self.note = note.into();
        self
    }
}

/// The empirical distribution of `values`: (value, share of values at most it).
pub fn cdf(values: &[f64]) -> Vec<(f64, f64)> {
    let mut sorted: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len() as f64;
    (sorted.iter().enumerate())
        .map(|(i, &v)| (v, (i + 1) as f64 / n))
        .collect()
}

/// At each request of `times_ms` (sorted or not), the requests in the window of `window_ms`
/// that ends with it: (minutes since the first request, times `scale`, count).
pub fn sliding_counts(times_ms: &[i128], window_ms: i128, scale: f64) -> Vec<(f64, f64)> {
    let mut times = times_ms.to_vec();
    times.sort_unstable();
    let Some(&first) = times.first() else {
        return Vec::new();
    };
    let mut out = Vec::with_capacity(times.len());
    let mut from = 0;
    for (i, &t) in times.iter().enumerate() {
        while times[from] <= t - window_ms {
            from += 1;
        }
        let minutes = (t - first) as f64 / 60_000.0 * scale;
        out.push((minutes, (i + 1 - from) as f64));
    }
    out
}

/// The runs of the fleet bench the report draws, by name.
const TIMELINES: [&str; 3] = ["original", "on-demand, as deployed", "spot-first, levers"];

/// `f` of each moment of `run`'s timeline, over hours since the first arrival, as `name`.
fn over_time(name: &str, run: &Report, f: &dyn Fn(&Moment) -> f64) -> Series {
    Series {
        name: name.into(),
        points: (run.timeline.iter())
            .map(|m| (m.at as f64 / 3600.0, f(m)))
            .collect(),
    }
}

/// The fleet bench's charts from its runs: the queue, the fleet in use and idle over the rush,
/// the waits, the start estimate's error, and the dollars per evaluation of every run.
pub fn fleet_charts(runs: &[(String, Report)]) -> Vec<Chart> {
    let run = |name: &str| runs.iter().find(|(n, _)| n == name).map(|(_, r)| r);
    let queue = TIMELINES
        .iter()
        .filter_map(|n| Some(over_time(n, run(n)?, &|m| f64::from(m.waiting))))
        .collect();
    let mut charts = vec![Chart::line(
        "queue",
        "Submissions waiting (arrived, not started)",
        ("hours since the first arrival", "submissions"),
        queue,
    )
    .noting("Ours holds each team to 2 evaluations and starts pairs as GPUs free; the original's way waits for whole nodes. Ours as deployed and with the levers queue alike: the levers change the bill, not the order (one line hides the other).")];
    for (id, name) in [
        ("fleet-ours", "spot-first, levers"),
        ("fleet-original", "original"),
    ] {
        let Some(r) = run(name) else { continue };
        let line = |label: &str, f: &dyn Fn(&Moment) -> f64| over_time(label, r, f);
        charts.push(
            Chart::line(
                id,
                &format!("The fleet, {name}: GPUs billed, pairs running, GPUs idle"),
                ("hours since the first arrival", "GPUs"),
                vec![
                    line("GPUs billed", &|m| f64::from(m.gpus)),
                    line("pairs running a route", &|m| f64::from(m.pairs)),
                    line("GPUs billed and idle", &|m| {
                        f64::from(m.gpus.saturating_sub(m.pairs))
                    }),
                    line("nodes", &|m| f64::from(m.nodes)),
                ],
            )
            .noting("Every GPU of a node is billed from its launch to its end; what runs no route is idle."),
        );
    }
    let waits = TIMELINES
        .iter()
        .filter_map(|n| {
            let minutes: Vec<f64> = run(n)?.waits.iter().map(|&w| w as f64 / 60.0).collect();
            Some(Series {
                name: (*n).into(),
                points: cdf(&minutes),
            })
        })
        .collect();
    charts.push(
        Chart::line(
            "waits",
            "Arrival -> first pair running (distribution)",
            ("minutes", "share of submissions"),
            waits,
        )
        .noting(
            "How long participants waited: the share of submissions that started within each wait.",
        ),
    );
    if let Some(r) = run("spot-first, levers") {
        let minutes = |misses: &[lb_domain::capacity::fleet::Miss]| {
            let errors: Vec<f64> = misses
                .iter()
                .map(|m| m.seconds.abs() as f64 / 60.0)
                .collect();
            cdf(&errors)
        };
        let errors = vec![
            Series {
                name: "forecast, the model's view".into(),
                points: minutes(&r.arrival_errors),
            },
            Series {
                name: "forecast, the admission table's (the note's)".into(),
                points: minutes(&r.table_errors),
            },
            Series {
                name: "pace (the note's fallback)".into(),
                points: minutes(&r.pace_errors),
            },
        ];
        charts.push(
            Chart::line(
                "estimates",
                "Start estimate at arrival: how far off (distribution)",
                ("minutes off the actual start", "share of submissions"),
                errors,
            )
            .noting("Spot first, levers. The target is a p90 of 25% of the median wait."),
        );
    }
    charts.push(Chart {
        kind: Kind::Bars,
        labels: runs.iter().map(|(n, _)| n.clone()).collect(),
        series: vec![Series {
            name: "dollars per evaluation".into(),
            points: (runs.iter().enumerate())
                .map(|(i, (_, r))| (i as f64, r.dollars_per_evaluation()))
                .collect(),
        }],
        ..Chart::line(
            "cost",
            "Dollars per evaluation, billed by the instance-second",
            ("", "dollars"),
            Vec::new(),
        )
        .noting("Each run of the fleet bench: the original's way, ours as deployed, each lever, and the Spot market's stresses.")
    });
    charts
}

/// What the EvalAI part of the bench saw of one rush.
#[derive(Debug, Clone, Default)]
pub struct EvalAiRush {
    /// The capacity it ran on.
    pub name: String,
    /// When EvalAI got each request (epoch milliseconds, real time).
    pub requests_ms: Vec<i128>,
    /// Arrival -> admitted, simulated minutes.
    pub admission: Vec<f64>,
    /// Arrival -> running, simulated minutes.
    pub start: Vec<f64>,
}

/// The EvalAI part's charts: requests in every sliding minute against EvalAI's limit, and
/// the waits of its queue. `window_ms` is its minute in real time, `scale` its speed-up.
pub fn evalai_charts(rushes: &[EvalAiRush], window_ms: i128, scale: f64, limit: u32) -> Vec<Chart> {
    let requests = rushes
        .iter()
        .map(|r| Series {
            name: r.name.clone(),
            points: sliding_counts(&r.requests_ms, window_ms, scale),
        })
        .collect();
    let waits = rushes
        .iter()
        .flat_map(|r| {
            [
                Series {
                    name: format!("{}: arrival -> admitted", r.name),
                    points: cdf(&r.admission),
                },
                Series {
                    name: format!("{}: arrival -> running", r.name),
                    points: cdf(&r.start),
                },
            ]
        })
        .collect();
    vec![
        Chart {
            limit: Some(Limit {
                label: format!("EvalAI's limit, {limit} a minute"),
                value: f64::from(limit),
            }),
            ..Chart::line(
                "evalai",
                "EvalAI requests in the sliding minute",
                ("simulated minutes", "requests in the minute before"),
                requests,
            )
            .noting("Every function takes its place from the shared budget before it asks EvalAI: no minute past the limit, no 429.")
        },
        Chart::line(
            "admission",
            "The admission queue: arrival -> admitted and -> running (distribution)",
            ("simulated minutes", "share of submissions"),
            waits,
        )
        .noting("Each team holds at most 2 places; a place given back wakes its team's next."),
    ]
}

/// The page: `title`, the bench's own text, and the charts drawn by its script.
pub fn page(title: &str, text: &str, charts: &[Chart]) -> String {
    let data = serde_json::json!({"charts": charts}).to_string();
    // Inside a script element nothing may close it.
    let data = data.replace('<', "\\u003c");
    let escape = |s: &str| {
        s.replace('&', "&amp;")
            .replace('<', "&lt;")
            .replace('>', "&gt;")
    };
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{title}</title>\n<style>{STYLE}</style></head>\n<body>\n<h1>{title}</h1>\n<div id=\"charts\"></div>\n<details><summary>The bench's text</summary><pre>{text}</pre></details>\n<script>const DATA = {data};\n{SCRIPT}</script>\n</body></html>\n",
        title = escape(title),
        text = escape(text),
    )
}

const STYLE: &str = "body{font:14px system-ui,sans-serif;margin:24px;color:#222;background:#fff}\
h1{font-size:20px}#charts{display:grid;grid-template-columns:repeat(auto-fill,minmax(560px,1fr));gap:20px}\
.chart{border:1px solid #ddd;border-radius:6px;padding:12px}.chart h2{font-size:15px;margin:0 0 4px}\
.chart p{margin:4px 0 0;color:#555;font-size:12px}.chart-error{color:#b00}\
.legend{font-size:12px;margin-top:6px}.legend span{margin-right:14px;white-space:nowrap}\
.legend i{display:inline-block;width:12px;height:3px;margin-right:4px;vertical-align:middle}\
pre{font-size:11px;overflow:auto}";

/// Draws every chart of `DATA` as SVG; each chart says it drew (`data-drawn`), the body how
/// many did and what failed (`data-charts-drawn`, `data-errors`).
const SCRIPT: &str = r#"
const COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#ff7f0e', '#9467bd', '#8c564b', '#17becf'];
const errors = [];
window.addEventListener('error', (e) => errors.push(String(e.message)));
const NS = 'http://www.w3.org/2000/svg';
function el(tag, attrs, parent) {
  const node = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}
function ticks(lo, hi, n) {
  if (hi <= lo) hi = lo + 1;
  const raw = (hi - lo) / n, mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(+v.toFixed(10));
  return out;
}
function frame(c, W, H) {
  const svg = el('svg', {viewBox: `0 0 ${W} ${H}`, width: '100%', role: 'img'});
  el('rect', {x: 0, y: 0, width: W, height: H, fill: '#fff'}, svg);
  return svg;
}
function lineChart(box, c) {
  const W = 540, H = 300, L = 56, R = 12, T = 10, B = 40;
  const pts = c.series.flatMap((s) => s.points);
  if (!pts.length) throw new Error('no points');
  let x0 = Math.min(...pts.map((p) => p[0])), x1 = Math.max(...pts.map((p) => p[0]));
  let y0 = Math.min(0, ...pts.map((p) => p[1])), y1 = Math.max(...pts.map((p) => p[1]));
  if (c.limit) y1 = Math.max(y1, c.limit.value * 1.1);
  if (x1 <= x0) x1 = x0 + 1;
  if (y1 <= y0) y1 = y0 + 1;
  const X = (x) => L + (x - x0) / (x1 - x0) * (W - L - R);
  const Y = (y) => H - B - (y - y0) / (y1 - y0) * (H - T - B);
  const svg = frame(c, W, H);
  for (const t of ticks(y0, y1, 5)) {
    el('line', {x1: L, x2: W - R, y1: Y(t), y2: Y(t), stroke: '#eee'}, svg);
    el('text', {x: L - 6, y: Y(t) + 4, 'text-anchor': 'end', 'font-size': 11}, svg).textContent = t;
  }
  for (const t of ticks(x0, x1, 6)) {
    el('text', {x: X(t), y: H - B + 16, 'text-anchor': 'middle', 'font-size': 11}, svg).textContent = t;
  }
  el('line', {x1: L, x2: W - R, y1: H - B, y2: H - B, stroke: '#888'}, svg);
  el('line', {x1: L, x2: L, y1: T, y2: H - B, stroke: '#888'}, svg);
  el('text', {x: (L + W - R) / 2, y: H - 6, 'text-anchor': 'middle', 'font-size': 12}, svg).textContent = c.x;
  el('text', {x: 12, y: (T + H - B) / 2, 'text-anchor': 'middle', 'font-size': 12,
              transform: `rotate(-90 12 ${(T + H - B) / 2})`}, svg).textContent = c.y;
  c.series.forEach((s, i) => {
    if (!s.points.length) return;
    const d = s.points.map((p, k) => `${k ? 'L' : 'M'}${X(p[0]).toFixed(1)},${Y(p[1]).toFixed(1)}`).join('');
    el('path', {d, fill: 'none', stroke: COLORS[i % COLORS.length], 'stroke-width': 1.6, class: 'series'}, svg);
  });
  if (c.limit) {
    el('line', {x1: L, x2: W - R, y1: Y(c.limit.value), y2: Y(c.limit.value), stroke: '#b00',
                'stroke-dasharray': '6 4', class: 'limit'}, svg);
    el('text', {x: W - R, y: Y(c.limit.value) - 4, 'text-anchor': 'end', 'font-size': 11, fill: '#b00'},
       svg).textContent = c.limit.label;
  }
  box.appendChild(svg);
  const legend = document.createElement('div');
  legend.className = 'legend';
  c.series.forEach((s, i) => {
    const item = document.createElement('span');
    item.innerHTML = `<i style="background:${COLORS[i % COLORS.length]}"></i>`;
    item.appendChild(document.createTextNode(s.name));
    legend.appendChild(item);
  });
  box.appendChild(legend);
}
function barChart(box, c) {
  const values = c.series[0].points.map((p) => p[1]);
  if (!values.length || values.length !== c.labels.length) throw new Error('labels and bars differ');
  const W = 540, row = 20, L = 190, R = 60, H = values.length * row + 10;
  const top = Math.max(...values) || 1;
  const svg = frame(c, W, H);
  values.forEach((v, i) => {
    const y = 5 + i * row;
    el('text', {x: L - 6, y: y + 14, 'text-anchor': 'end', 'font-size': 11}, svg).textContent = c.labels[i];
    el('rect', {x: L, y: y + 3, height: row - 6, width: Math.max(1, v / top * (W - L - R)),
                fill: COLORS[i % COLORS.length], class: 'series'}, svg);
    el('text', {x: L + v / top * (W - L - R) + 4, y: y + 14, 'font-size': 11}, svg).textContent = v.toFixed(2);
  });
  box.appendChild(svg);
}
let drawn = 0;
for (const c of DATA.charts) {
  const box = document.createElement('div');
  box.className = 'chart';
  box.id = c.id;
  const h = document.createElement('h2');
  h.textContent = c.title;
  box.appendChild(h);
  document.getElementById('charts').appendChild(box);
  try {
    (c.kind === 'bars' ? barChart : lineChart)(box, c);
    const p = document.createElement('p');
    p.textContent = c.note;
    box.appendChild(p);
    box.dataset.drawn = 'true';
    drawn += 1;
  } catch (e) {
    errors.push(`${c.id}: ${e.message}`);
    box.classList.add('chart-error');
    box.appendChild(document.createTextNode(`This chart could not be drawn: ${e.message}`));
  }
}
document.body.dataset.chartsDrawn = String(drawn);
document.body.dataset.charts = String(DATA.charts.length);
document.body.dataset.errors = errors.join('; ');
// Errors thrown after this script (none are expected) are said too, once they happen.
window.addEventListener('error', () => { document.body.dataset.errors = errors.join('; '); });
"#;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sliding_minute_counts_the_requests_that_end_in_it() {
        let times = [0, 10_000, 59_999, 60_000, 130_000];
        let counts: Vec<f64> = sliding_counts(&times, 60_000, 1.0)
            .iter()
            .map(|p| p.1)
            .collect();
        assert_eq!(counts, [1.0, 2.0, 3.0, 3.0, 1.0]);
        assert_eq!(
            cdf(&[3.0, 1.0, 2.0, f64::NAN]),
            [(1.0, 1.0 / 3.0), (2.0, 2.0 / 3.0), (3.0, 1.0)]
        );
        let page = page("t</title>", "<b>", &[]);
        assert!(page.contains("t&lt;/title&gt;") && page.contains("&lt;b&gt;"));
    }
}
