//! `colf-sheet`: tile PNGs into a contact sheet.

use crate::sheet::{enlarge, load_tile, tile};
use anyhow::Result;
use clap::Parser;

/// Tile PNGs into one contact-sheet PNG.
#[derive(Parser, Debug)]
#[command(
    name = "colf-sheet",
    version,
    about = "Tile PNG images (and label masks, in colour) into one contact sheet",
    long_about = "Tile PNG images row-major into a grid of --cols columns, white gaps between \
cells, and write one PNG. Files whose name ends in .mask.png are label masks (0 = background, \
k = object or slot k): they are shown with one distinct colour per label (background black) \
instead of as near-black grey. The word `-` in the list leaves a cell empty, so rows can be \
aligned. Tiles of different sizes sit at the top left of cells of the largest size.\n\n\
PNG inputs may hold at most 67108864 pixels (8192²) and 512 MiB of decoded pixels, and the \
sheet (after --scale) at most 67108864 pixels; both are checked from the PNG headers before any \
tile is decoded.",
    after_help = "Example:\n  colf-sheet --cols 5 input.png orbit/frame_000{0,1,2,3}.png - orbit/frame_000{0,1,2,3}.mask.png -o sheet.png"
)]
pub struct SheetArgs {
    /// PNG files (`-`: an empty cell).
    #[arg(value_name = "PNG", required = true)]
    pub images: Vec<String>,

    /// Number of columns.
    #[arg(long, default_value_t = 4, value_name = "N")]
    pub cols: usize,

    /// Enlarge every tile N times (pixel replication), e.g. 64² renders to 192².
    #[arg(long, default_value_t = 1, value_name = "N",
          value_parser = clap::value_parser!(u32).range(1..=16))]
    pub scale: u32,

    /// Gap between cells, in pixels.
    #[arg(long, default_value_t = 4, value_name = "PX")]
    pub gap: u32,

    /// Output PNG (`-`: stdout, refused on a terminal).
    #[arg(short, long, value_name = "OUT")]
    pub output: String,
}

/// Runs `colf-sheet`.
pub fn run(args: &SheetArgs) -> Result<()> {
    // The sheet's size from the PNG headers first: a sheet too large is refused before any
    // tile is decoded.
    let files = args
        .images
        .iter()
        .map(|path| {
            if path == "-" {
                return Ok(None);
            }
            let bytes = crate::io::read_input(path, true)?;
            let size = crate::image_io::png_dimensions(&bytes, path)?;
            Ok(Some((bytes, size)))
        })
        .collect::<Result<Vec<_>>>()?;
    let sizes: Vec<Option<(u32, u32)>> = files.iter().map(|f| f.as_ref().map(|f| f.1)).collect();
    crate::sheet::sheet_size(&sizes, args.cols, args.gap, args.scale)?;
    let tiles = args
        .images
        .iter()
        .enumerate()
        .map(|(i, path)| {
            if path == "-" {
                return Ok(None);
            }
            let bytes = &files[i].as_ref().expect("read above").0;
            let tile = load_tile(bytes, path, path.ends_with(".mask.png"))?;
            Ok(Some(enlarge(&tile, args.scale, path)?))
        })
        .collect::<Result<Vec<_>>>()?;
    let sheet = tile(&tiles, args.cols, args.gap)?;
    let png = crate::image_io::encode_png_rgb(sheet.w, sheet.h, &sheet.data);
    crate::io::write_output(&args.output, &png, true)
}
