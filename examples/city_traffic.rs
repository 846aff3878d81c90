//! `make demo-city`'s merge: the cars of several encoded streets lined up in the lanes of one.
//!
//! Reads codes files of `city-block` streets (from `colf-encode` with `--camera`, so every slot
//! lives in world space) and prints, on stdout, a `colf-edit` script that — applied to the first
//! file — merges the others' slots into it and moves every slot to its own place in `--lanes`
//! (world y of each lane), spread evenly from `--from` to `--to` along the street (world x), in
//! the order of the slots' x along their own streets. A slot that changes side of the road is
//! turned 180° about its own vertical, so cars on each side face the same way. The slots keep
//! their height. Refused when the places would lie closer than `--min-gap` (a car is at most
//! 4.8 long).
//!
//! Usage: `city_traffic [--lanes -5.5,-1.8,1.8,5.5] [--from -28] [--to 142] [--min-gap 5.5]
//!         STREET.codes...`, then `colf-edit EDITS STREET0.codes -o merged.codes`.

use anyhow::{bail, Context, Result};
use colf::codes::Codes;
use serde_json::{json, Value};

struct Args {
    lanes: Vec<f64>,
    from: f64,
    to: f64,
    min_gap: f64,
    streets: Vec<String>,
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        lanes: vec![-5.5, -1.8, 1.8, 5.5],
        from: -28.0,
        to: 142.0,
        min_gap: 5.5,
        streets: Vec::new(),
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < argv.len() {
        let flag = argv[i].as_str();
        if !flag.starts_with("--") {
            a.streets.push(argv[i].clone());
            i += 1;
            continue;
        }
        let val = argv
            .get(i + 1)
            .with_context(|| format!("{flag} needs a value"))?;
        let number = |s: &str| -> Result<f64> {
            let x: f64 = s
                .trim()
                .parse()
                .with_context(|| format!("{flag}: `{s}` is not a number"))?;
            if !x.is_finite() {
                bail!("{flag}: `{s}` is not a finite number");
            }
            Ok(x)
        };
        match flag {
            "--lanes" => a.lanes = val.split(',').map(number).collect::<Result<_>>()?,
            "--from" => a.from = number(val)?,
            "--to" => a.to = number(val)?,
            "--min-gap" => a.min_gap = number(val)?,
            other => bail!("unknown argument {other}"),
        }
        i += 2;
    }
    if a.streets.is_empty() {
        bail!("no codes files given (usage: city_traffic [--lanes Y,...] STREET.codes...)");
    }
    if a.lanes.is_empty() || a.to <= a.from {
        bail!("--lanes needs at least one lane and --to must lie beyond --from");
    }
    Ok(a)
}

/// One slot of the merged scene: its index there and where it stands.
struct Car {
    index: usize,
    x: f64,
    y: f64,
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let mut ops: Vec<Value> = Vec::new();
    let mut cars = Vec::new();
    for (file, path) in args.streets.iter().enumerate() {
        let codes = Codes::read(path)?;
        if file > 0 {
            ops.push(json!({"op": "merge", "from": path, "comment": format!("street {file}")}));
        }
        for slot in &codes.slots {
            let origin = slot.slot_to_world.w_axis;
            cars.push(Car {
                index: cars.len(),
                x: origin.x,
                y: origin.y,
            });
        }
    }
    // Places: lane by lane at each position along the street, nearest first.
    let lanes = args.lanes.len();
    let per_lane = cars.len().div_ceil(lanes).max(1);
    let gap = if per_lane > 1 {
        (args.to - args.from) / (per_lane - 1) as f64
    } else {
        0.0
    };
    if per_lane > 1 && gap < args.min_gap {
        bail!(
            "{} slots need {per_lane} places a lane in {lanes} lanes: {gap:.2} apart from {} to {}, under --min-gap {}",
            cars.len(),
            args.from,
            args.to,
            args.min_gap
        );
    }
    cars.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.index.cmp(&b.index)));
    for (place, car) in cars.iter().enumerate() {
        let x = args.from + gap * (place / lanes) as f64;
        let y = args.lanes[place % lanes];
        ops.push(json!({
            "op": "translate",
            "slots": [car.index],
            "by": [x - car.x, y - car.y, 0.0],
        }));
        if (y < 0.0) != (car.y < 0.0) {
            // A car that crossed the road faces the way its new side's traffic does (a turn
            // about the vertical through its new place: the pivot's height does not matter).
            ops.push(json!({
                "op": "rotate",
                "slots": [car.index],
                "axis": [0, 0, 1],
                "degrees": 180,
                "pivot": [x, y, 0.0],
            }));
        }
    }
    eprintln!(
        "city_traffic: {} slots from {} streets in {lanes} lanes, {per_lane} places a lane {gap:.2} apart",
        cars.len(),
        args.streets.len()
    );
    println!("{}", serde_json::to_string_pretty(&json!({ "ops": ops }))?);
    Ok(())
}
