//! Reading and writing CFAs: `cfa.npy` (uint8 codes, see docs/capture-format.md) and colour
//! PNG pictures of the filter layout (pure red, green, blue = colour filters, white = W), the
//! format of the real sensor's `rgbw_oh_bn_color_ss2_corrected.png` (paper §6, colour SPAD).
#![forbid(unsafe_code)]

use super::Cfa;
use crate::atomic::write_atomic_synced;
use crate::error::{Error, Result};
use image::{Rgb, RgbImage};
use ndarray::Array2;
use ndarray_npy::{ReadNpyExt, WriteNpyExt};
use std::fs::File;

use std::path::Path;

/// The colour a PNG uses for each channel, indexed by [`super::Channel::index`].
const CHANNEL_RGB: [[u8; 3]; 4] = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]];

/// Converts an RGB picture of a CFA into a [`Cfa`]: pure red (255,0,0), green (0,255,0) and
/// blue (0,0,255) are R, G, B filters, white (255,255,255) is W. Any other colour is an error
/// naming `source` (the file the picture came from) and the pixel.
pub fn from_rgb_image(img: &RgbImage, source: impl AsRef<Path>) -> Result<Cfa> {
    let (w, h) = img.dimensions();
    if w == 0 || h == 0 {
        return Err(Error::format(source, "CFA picture is empty"));
    }
    let mut codes = Array2::<u8>::zeros((h as usize, w as usize));
    for (x, y, px) in img.enumerate_pixels() {
        let code = CHANNEL_RGB.iter().position(|c| *c == px.0).ok_or_else(|| {
            Error::format(
                source.as_ref(),
                format!(
                    "pixel (y={y}, x={x}) has colour ({}, {}, {}); a CFA picture may hold only \
                     pure red, green, blue or white",
                    px.0[0], px.0[1], px.0[2]
                ),
            )
        })?;
        codes[[y as usize, x as usize]] = code as u8;
    }
    Cfa::new(codes)
}

/// Renders `cfa` as an RGB picture: R, G, B filters as pure red, green, blue, W as white.
/// The inverse of [`from_rgb_image`].
pub fn to_rgb_image(cfa: &Cfa) -> RgbImage {
    RgbImage::from_fn(cfa.width() as u32, cfa.height() as u32, |x, y| {
        Rgb(CHANNEL_RGB[cfa.codes()[[y as usize, x as usize]] as usize])
    })
}

/// Loads a CFA picture (PNG or any format the `image` crate reads) with [`from_rgb_image`].
/// An alpha channel, if present, must be opaque.
pub fn load_png(path: impl AsRef<Path>) -> Result<Cfa> {
    let path = path.as_ref();
    let img = image::open(path).map_err(|e| image_error(path, e))?;
    if img.color().has_alpha() {
        let rgba = img.to_rgba8();
        if let Some((x, y, p)) = rgba.enumerate_pixels().find(|(_, _, p)| p.0[3] != 255) {
            return Err(Error::format(
                path,
                format!(
                    "pixel (y={y}, x={x}) has alpha {}; a CFA picture must be opaque",
                    p.0[3]
                ),
            ));
        }
    }
    from_rgb_image(&img.to_rgb8(), path)
}

/// Loads `cfa.npy` (uint8 `(H, W)`, codes 0=R 1=G 2=B 3=W).
pub fn load_npy(path: impl AsRef<Path>) -> Result<Cfa> {
    let path = path.as_ref();
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let codes = Array2::<u8>::read_npy(std::io::BufReader::new(file))
        .map_err(|e| Error::format(path, format!("not a uint8 2-D .npy CFA: {e}")))?;
    Cfa::new(codes).map_err(|e| Error::format(path, e.to_string()))
}

/// Loads a CFA from `.npy` codes or a colour picture, chosen by the file extension.
pub fn load(path: impl AsRef<Path>) -> Result<Cfa> {
    let path = path.as_ref();
    match extension(path).as_deref() {
        Some("npy") => load_npy(path),
        _ => load_png(path),
    }
}

/// Writes `cfa` as `.npy` codes or a colour `.png`, chosen by the extension of `path`, through a
/// temporary file renamed into place (a reader never sees a half-written file).
pub fn save(cfa: &Cfa, path: impl AsRef<Path>) -> Result<()> {
    let path = path.as_ref();
    match extension(path).as_deref() {
        Some("npy") => write_atomic_synced(path, |w| {
            cfa.codes()
                .write_npy(w)
                .map_err(|e| std::io::Error::other(e.to_string()))
        }),
        Some("png") => save_png(&to_rgb_image(cfa), path),
        _ => Err(Error::format(
            path,
            "unknown CFA output type: the extension must be .npy or .png",
        )),
    }
}

/// Writes any 8-bit image as PNG atomically (temporary file, then rename).
pub fn save_png<P, C>(img: &image::ImageBuffer<P, C>, path: impl AsRef<Path>) -> Result<()>
where
    P: image::PixelWithColorType<Subpixel = u8>,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [u8]>,
{
    let path = path.as_ref();
    // The PNG encoder needs a seekable writer: encode in memory, then write atomically.
    let mut png = std::io::Cursor::new(Vec::new());
    img.write_to(&mut png, image::ImageFormat::Png)
        .map_err(|e| Error::io(path, std::io::Error::other(e.to_string())))?;
    write_atomic_synced(path, |w| w.write_all(png.get_ref()))
}

/// Writes a text file atomically.
pub fn save_text(text: &str, path: impl AsRef<Path>) -> Result<()> {
    write_atomic_synced(path.as_ref(), |w| w.write_all(text.as_bytes()))
}

fn extension(path: &Path) -> Option<String> {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
}

fn image_error(path: &Path, e: image::ImageError) -> Error {
    match e {
        image::ImageError::IoError(io) => Error::io(path, io),
        other => Error::format(path, format!("corrupt or unsupported image: {other}")),
    }
}
