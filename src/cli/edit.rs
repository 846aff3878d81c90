//! `colf-edit`: apply JSON edits to a codes file, or summarise one.

use crate::codes::Codes;
use crate::edit::{apply_edits, inspect, parse_edits};
use crate::io::{display_name, read_input, write_output};
use anyhow::{bail, Result};
use clap::Parser;

/// Move, rotate, delete, duplicate and merge the object slots of a codes file.
#[derive(Parser, Debug)]
#[command(
    name = "colf-edit",
    version,
    about = "Edit the object slots of a colf codes file with a JSON script",
    long_about = "Apply a JSON list of edit ops to a codes file (from colf-encode) and write the \
edited codes. Ops run in order; slot indices refer to the slots as they stand when the op runs; \
\"slots\": \"all\" selects every slot, and \"slots\": {\"near\": [x, y, z], \"within\": r} the one \
slot whose frame origin (--inspect's `origin`) lies nearest that point (ties: the first; \"within\" \
is optional and refuses a point with no slot that close), so a script can name an object by \
where it stands; with \"seen_from\": [x, y, z] (a camera's position) the distance is from the line \
of sight from there through the point, as an encoding from one view knows an object's direction \
better than its depth; vectors are world units, angles degrees.\n\n\
EDITS is {\"ops\": [...]} or a bare array of ops:\n\n\
  {\"op\": \"translate\", \"slots\": [2], \"by\": [1, 0, 0]}\n\n\
  {\"op\": \"rotate\", \"slots\": [1], \"axis\": [0, 0, 1], \"degrees\": 90, \"pivot\": [0, 0, 0]}\n\n\
  {\"op\": \"delete\", \"slots\": [4]}\n\n\
  {\"op\": \"keep\", \"slots\": [0, 1]}\n\n\
  {\"op\": \"duplicate\", \"slots\": [1], \"by\": [0, 2, 0]}\n\n\
  {\"op\": \"merge\", \"from\": \"other.codes.safetensors\", \"slots\": [0, 2]}\n\n\
  {\"op\": \"background\", \"from\": \"other.codes.safetensors\"}\n\n\
  {\"op\": \"prune\", \"min_mass\": 0.02}\n\n\
translate and rotate left-multiply each slot's slot_to_world by the world-space transform \
(rotate turns about `axis` through `pivot`, default the origin); duplicate appends moved copies; \
merge appends another file's slots in their own frames (\"slots\" defaults to all); background \
replaces the background latent; prune drops slots whose encoding attention mass is below \
min_mass. merge and background refuse codes from another model. Paths in `from` are relative to \
the current directory. An op may carry a free-form \"comment\" field; any other unknown field is \
an error.\n\n\
A bad op is reported as `colf-edit: error: EDITS: op N (name): field `f`: ...` and nothing is \
written: the output file, if any, is replaced atomically only on success.\n\n\
With --inspect, the only positional argument is the codes file, and a JSON summary (model, \
latent size, and per slot: index, mass, frame origin, source) is printed on stdout.",
    after_help = "Examples:\n  colf-edit moves.json scene.codes -o moved.codes\n  \
colf-encode a.png -o - | colf-edit moves.json | colf-render - --cameras orbit.json --out out/\n  \
colf-edit --inspect scene.codes"
)]
pub struct EditArgs {
    /// JSON edits file (`-` for stdin). With --inspect: the codes file.
    #[arg(value_name = "EDITS", required_unless_present = "inspect")]
    pub edits: Option<String>,

    /// Codes file to edit (`-` or omitted: stdin).
    #[arg(value_name = "CODES", conflicts_with = "inspect")]
    pub codes: Option<String>,

    /// Where to write the edited codes (`-`: stdout, the default; refused on a terminal).
    #[arg(short, long, value_name = "OUT", default_value = "-")]
    pub output: String,

    /// Print a JSON summary of the slots of CODES instead of editing.
    #[arg(long)]
    pub inspect: bool,
}

/// Runs `colf-edit`.
pub fn run(args: &EditArgs) -> Result<()> {
    if args.inspect {
        if args.codes.is_some() {
            bail!("--inspect takes one codes file, not an edits file and a codes file");
        }
        let codes = Codes::read(args.edits.as_deref().unwrap_or("-"))?;
        let text = serde_json::to_string_pretty(&inspect(&codes))? + "\n";
        return write_output("-", text.as_bytes(), false);
    }
    let Some(edits_path) = args.edits.as_deref() else {
        bail!("missing the EDITS file (see --help)");
    };
    let codes_path = args.codes.as_deref().unwrap_or("-");
    if edits_path == "-" && codes_path == "-" {
        return Err(crate::cli::both_stdin("EDITS", "CODES"));
    }
    // Parse every op before touching any file: a bad script writes nothing.
    let ops = parse_edits(&read_input(edits_path, false)?, display_name(edits_path))?;
    let codes = Codes::read(codes_path)?;
    let edited = apply_edits(&codes, &ops, display_name(edits_path))?;
    edited.write(&args.output)
}
