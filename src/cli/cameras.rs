//! `colf-cameras`: write camera paths (`transforms.json`) for novel-view renders.

use crate::camera_path::{line, orbit, Lens};
use crate::io::write_output;
use anyhow::{anyhow, Result};
use clap::{Args, Parser, Subcommand};
use glam::DVec3;

/// Write a camera path as transforms.json.
#[derive(Parser, Debug)]
#[command(
    name = "colf-cameras",
    version,
    about = "Write camera paths (orbit, dolly) as transforms.json for colf-render",
    long_about = "Write a camera path in the NeRF transforms.json convention (camera-to-world, \
OpenGL camera axes, world +Z up) so that a novel-view render needs no hand-written JSON. \
Frames are named frame_0000.png, frame_0001.png, ...; colf-render names its outputs after them.\n\n\
The defaults match the clevr567 training cameras of colf-synth: distance 12.4 from the origin, \
elevation 40 degrees, 64x64 pixels, horizontal field of view 49.13 degrees.",
    after_help = "Examples:\n  colf-cameras orbit --frames 36 --size 128 -o orbit.json\n  \
colf-cameras orbit | colf-render scene.codes --cameras - --out orbit/\n  \
colf-cameras line --from 12,0,8 --to 6,0,4 --frames 24 -o dolly.json"
)]
pub struct CamerasArgs {
    #[command(subcommand)]
    pub path: PathKind,
}

/// Image size and lens, shared by every path.
#[derive(Args, Debug, Clone)]
pub struct LensArgs {
    /// Image width in pixels.
    #[arg(long, default_value_t = 64, value_name = "W", value_parser = crate::cli::parse::image_side)]
    pub size: u32,
    /// Image height in pixels (default: the width).
    #[arg(long, value_name = "H", value_parser = crate::cli::parse::image_side)]
    pub height: Option<u32>,
    /// Horizontal field of view in degrees.
    #[arg(long, default_value_t = 49.13, value_name = "DEG", value_parser = crate::cli::parse::fov_degrees)]
    pub fov: f64,
    /// Where to write transforms.json (`-`: stdout).
    #[arg(short, long, default_value = "-", value_name = "OUT")]
    pub output: String,
}

#[derive(Subcommand, Debug)]
pub enum PathKind {
    /// Cameras on a circle about a centre, all looking at it.
    Orbit {
        /// Point the cameras look at.
        #[arg(long, default_value = "0,0,0", value_parser = parse_vec3, value_name = "X,Y,Z")]
        center: DVec3,
        /// Distance from the centre.
        #[arg(long, default_value_t = 12.4, value_name = "R", value_parser = crate::cli::parse::positive)]
        radius: f64,
        /// Elevation above the centre's horizontal plane, degrees.
        #[arg(
            long,
            default_value_t = 40.0,
            value_name = "DEG",
            allow_negative_numbers = true,
            value_parser = crate::cli::parse::elevation_degrees
        )]
        elevation: f64,
        /// Azimuth of the first frame, degrees (0 = the +X axis).
        #[arg(
            long,
            default_value_t = 0.0,
            value_name = "DEG",
            allow_negative_numbers = true,
            value_parser = crate::cli::parse::finite
        )]
        start_azimuth: f64,
        /// Number of frames (evenly spaced over 360 degrees).
        #[arg(long, default_value_t = 36, value_name = "N", value_parser = crate::cli::parse::path_frames)]
        frames: usize,
        #[command(flatten)]
        lens: LensArgs,
    },
    /// A dolly: cameras on a straight line between two positions.
    Line {
        /// First camera position.
        #[arg(long, value_parser = parse_vec3, value_name = "X,Y,Z", allow_hyphen_values = true)]
        from: DVec3,
        /// Last camera position.
        #[arg(long, value_parser = parse_vec3, value_name = "X,Y,Z", allow_hyphen_values = true)]
        to: DVec3,
        /// Point the first camera looks at.
        #[arg(long, default_value = "0,0,0", value_parser = parse_vec3, value_name = "X,Y,Z", allow_hyphen_values = true)]
        look_at: DVec3,
        /// Point the last camera looks at (default: --look-at); the target moves linearly.
        #[arg(long, value_parser = parse_vec3, value_name = "X,Y,Z", allow_hyphen_values = true)]
        look_at_end: Option<DVec3>,
        /// Number of frames, both ends included.
        #[arg(long, default_value_t = 24, value_name = "N", value_parser = crate::cli::parse::path_frames)]
        frames: usize,
        #[command(flatten)]
        lens: LensArgs,
    },
}

/// Parses `X,Y,Z`.
pub fn parse_vec3(text: &str) -> std::result::Result<DVec3, String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!("expected X,Y,Z, got `{text}`"));
    }
    let mut v = [0.0; 3];
    for (o, p) in v.iter_mut().zip(&parts) {
        *o = p
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("`{p}` is not a finite number"))?;
    }
    Ok(DVec3::from_array(v))
}

fn lens(args: &LensArgs) -> Lens {
    Lens {
        width: args.size,
        height: args.height.unwrap_or(args.size),
        fov_x_degrees: args.fov,
    }
}

/// Runs `colf-cameras`.
pub fn run(args: &CamerasArgs) -> Result<()> {
    let (cameras, output) = match &args.path {
        PathKind::Orbit {
            center,
            radius,
            elevation,
            start_azimuth,
            frames,
            lens: l,
        } => (
            orbit(
                *center,
                *radius,
                *elevation,
                *start_azimuth,
                *frames,
                lens(l),
            ),
            &l.output,
        ),
        PathKind::Line {
            from,
            to,
            look_at,
            look_at_end,
            frames,
            lens: l,
        } => (
            line(
                *from,
                *to,
                *look_at,
                look_at_end.unwrap_or(*look_at),
                *frames,
                lens(l),
            ),
            &l.output,
        ),
    };
    let cameras = cameras.map_err(|e| anyhow!("{e:#}"))?;
    let json = cameras.to_json();
    // The reader's own checks, so colf-cameras never writes what colf-render refuses.
    crate::camera::Cameras::from_json(json.as_bytes(), "the cameras to write")?;
    write_output(output, json.as_bytes(), false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_range_values_are_usage_errors() {
        for flags in [
            &["orbit", "--frames", "0"][..],
            &["orbit", "--size", "0"],
            &["orbit", "--fov", "180"],
            &["orbit", "--radius", "-1"],
            &["orbit", "--elevation", "90"],
            &["line", "--from", "1,0,0", "--to", "2,0,0", "--frames", "0"],
        ] {
            let err = CamerasArgs::try_parse_from([&["colf-cameras"], flags].concat()).unwrap_err();
            assert_eq!(err.exit_code(), 2, "{flags:?}");
        }
    }
}
