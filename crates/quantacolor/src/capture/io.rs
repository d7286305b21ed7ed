//! Typed `.npy` readers/writers and image files shared by every writer. Every output is
//! written atomically through [`crate::atomic`]. Every error names the file and the problem.
#![forbid(unsafe_code)]

use super::npy::NpyHeader;
use crate::atomic::write_atomic;
use crate::error::{Error, Result};
use image::{DynamicImage, ImageBuffer, ImageFormat, Rgb};
use ndarray::{Array2, Array3, ArrayBase, Data, Dimension, Ix2, Ix3};
use ndarray_npy::{ReadNpyError, ReadNpyExt, ReadableElement, WritableElement, WriteNpyExt};
use std::fs;
use std::io::{self, Cursor};
use std::path::Path;

/// Writes `array` as a `.npy` file (NumPy format, C order), atomically.
pub fn write_npy<A, S, D>(path: impl AsRef<Path>, array: &ArrayBase<S, D>) -> Result<()>
where
    A: WritableElement,
    S: Data<Elem = A>,
    D: Dimension,
{
    write_atomic(path, |w| {
        array
            .write_npy(w)
            .map_err(|e| io::Error::other(format!("cannot write .npy: {e}")))
    })
}

/// A NumPy-style name for `T`, for error messages.
fn dtype_name<T>() -> String {
    match std::any::type_name::<T>() {
        "bool" => "bool ('|b1')".into(),
        "u8" => "uint8 ('|u1')".into(),
        "u16" => "uint16 ('<u2')".into(),
        "u32" => "uint32 ('<u4')".into(),
        "i32" => "int32 ('<i4')".into(),
        "f32" => "float32 ('<f4')".into(),
        "f64" => "float64 ('<f8')".into(),
        other => other.into(),
    }
}

/// Reads a `.npy` of element type `T` and rank `D::NDIM`. The header is checked against the
/// file size before anything is allocated, so a corrupt header cannot ask for terabytes.
fn read_npy_typed<T, D>(path: &Path) -> Result<ndarray::Array<T, D>>
where
    T: ReadableElement,
    D: Dimension,
{
    let bytes = fs::read(path).map_err(|e| Error::io(path, e))?;
    let header = NpyHeader::parse(&bytes).map_err(|m| Error::format(path, m))?;
    let ndim = D::NDIM.expect("fixed-rank arrays only");
    if header.shape.len() != ndim {
        return Err(Error::format(
            path,
            format!(
                "expected a {ndim}-D array of {}, found shape {:?}",
                dtype_name::<T>(),
                header.shape
            ),
        ));
    }
    let item = header.item_size().ok_or_else(|| {
        Error::format(
            path,
            format!(
                "unsupported dtype '{}' (expected {})",
                header.descr,
                dtype_name::<T>()
            ),
        )
    })?;
    let available = bytes.len() - header.data_offset;
    let needed = header.element_count().and_then(|n| n.checked_mul(item));
    if !matches!(needed, Some(n) if n <= available) {
        return Err(Error::format(
            path,
            format!(
                "file is truncated: shape {:?} of '{}' needs {} data bytes, the file holds {available}",
                header.shape,
                header.descr,
                needed.map_or("more than usize::MAX".to_string(), |n| n.to_string()),
            ),
        ));
    }
    ndarray::Array::<T, D>::read_npy(&bytes[..]).map_err(|e| {
        let message = match e {
            ReadNpyError::WrongDescriptor(d) => {
                format!("dtype {d} found, expected {}", dtype_name::<T>())
            }
            ReadNpyError::WrongNdim(want, got) => {
                format!("expected a {want:?}-D array, found {got}-D")
            }
            ReadNpyError::MissingData | ReadNpyError::Io(_) => {
                "file is truncated (data ends early)".to_string()
            }
            ReadNpyError::ExtraBytes(n) => format!("{n} unexpected bytes after the array data"),
            ReadNpyError::ParseHeader(e) => format!("corrupt .npy header: {e}"),
            ReadNpyError::ParseData(e) => format!("corrupt array data: {e}"),
            other => format!("cannot read .npy: {other}"),
        };
        Error::format(path, message)
    })
}

/// Reads a 2-D `.npy` of element type `T` (e.g. a CFA or a hot-pixel mask); a wrong dtype, rank
/// or a truncated file is an [`Error::Format`] naming `path`.
pub fn read_npy_2d<T: ReadableElement>(path: impl AsRef<Path>) -> Result<Array2<T>> {
    read_npy_typed::<T, Ix2>(path.as_ref())
}

/// Reads a 3-D `.npy` of element type `T` (e.g. a ground-truth image (H, W, 3)).
pub fn read_npy_3d<T: ReadableElement>(path: impl AsRef<Path>) -> Result<Array3<T>> {
    read_npy_typed::<T, Ix3>(path.as_ref())
}

/// Reads a 4-D `.npy` of element type `T` (e.g. a video stack (N, H, W, 3)).
pub fn read_npy_4d<T: ReadableElement>(path: impl AsRef<Path>) -> Result<ndarray::Array4<T>> {
    read_npy_typed::<T, ndarray::Ix4>(path.as_ref())
}

/// The (H, W) of an (H, W, 3) image array, or an error naming `path`.
fn rgb_dims<T>(path: &Path, image: &Array3<T>) -> Result<(u32, u32)> {
    let (h, w, c) = image.dim();
    if c != 3 || h == 0 || w == 0 {
        return Err(Error::invalid(format!(
            "{}: an RGB image must have shape (H, W, 3) with H, W > 0, got {:?}",
            path.display(),
            image.dim()
        )));
    }
    let fit = |n: usize| u32::try_from(n).map_err(|_| Error::invalid("image too large"));
    Ok((fit(w)?, fit(h)?))
}

/// Row-major (H, W, 3) samples as one interleaved vector.
fn interleaved<T: Copy>(image: &Array3<T>) -> Vec<T> {
    image.iter().copied().collect()
}

/// Encodes `image` as `format` in memory (errors name `path`).
fn encode(path: &Path, image: DynamicImage, format: ImageFormat) -> Result<Vec<u8>> {
    let mut encoded = Cursor::new(Vec::new());
    image
        .write_to(&mut encoded, format)
        .map_err(|e| Error::format(path, format!("cannot encode {format:?}: {e}")))?;
    Ok(encoded.into_inner())
}

/// Encodes `image` as `format` in memory, then writes it atomically.
fn write_encoded(path: &Path, image: DynamicImage, format: ImageFormat) -> Result<()> {
    let bytes = encode(path, image, format)?;
    write_atomic(path, |w| w.write_all(&bytes))
}

/// The bytes of an 8-bit sRGB PNG of (H, W, 3) samples (what [`write_png_rgb8`] writes).
pub fn encode_png_rgb8(image: &Array3<u8>) -> Result<Vec<u8>> {
    let path = Path::new("<in-memory PNG>");
    let (w, h) = rgb_dims(path, image)?;
    let buf =
        ImageBuffer::<Rgb<u8>, _>::from_raw(w, h, interleaved(image)).expect("length matches dims");
    encode(path, DynamicImage::ImageRgb8(buf), ImageFormat::Png)
}

/// Writes an 8-bit sRGB PNG from (H, W, 3) samples.
pub fn write_png_rgb8(path: impl AsRef<Path>, image: &Array3<u8>) -> Result<()> {
    let path = path.as_ref();
    rgb_dims(path, image)?;
    let bytes = encode_png_rgb8(image)?;
    write_atomic(path, |w| w.write_all(&bytes))
}

/// Writes a 16-bit PNG from (H, W, 3) samples.
pub fn write_png_rgb16(path: impl AsRef<Path>, image: &Array3<u16>) -> Result<()> {
    let path = path.as_ref();
    let (w, h) = rgb_dims(path, image)?;
    let buf = ImageBuffer::<Rgb<u16>, _>::from_raw(w, h, interleaved(image))
        .expect("length matches dims");
    write_encoded(path, DynamicImage::ImageRgb16(buf), ImageFormat::Png)
}

/// Writes a 16-bit TIFF from (H, W, 3) samples.
pub fn write_tiff_rgb16(path: impl AsRef<Path>, image: &Array3<u16>) -> Result<()> {
    let path = path.as_ref();
    let (w, h) = rgb_dims(path, image)?;
    let buf = ImageBuffer::<Rgb<u16>, _>::from_raw(w, h, interleaved(image))
        .expect("length matches dims");
    write_encoded(path, DynamicImage::ImageRgb16(buf), ImageFormat::Tiff)
}

/// Writes a linear float OpenEXR from (H, W, 3) samples.
pub fn write_exr_rgb(path: impl AsRef<Path>, image: &Array3<f32>) -> Result<()> {
    let path = path.as_ref();
    let (w, h) = rgb_dims(path, image)?;
    let buf = ImageBuffer::<Rgb<f32>, _>::from_raw(w, h, interleaved(image))
        .expect("length matches dims");
    write_encoded(path, DynamicImage::ImageRgb32F(buf), ImageFormat::OpenExr)
}

/// How the values returned by [`read_rgb_image`] are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelEncoding {
    /// Display-referred sRGB-encoded values in [0, 1] (8/16-bit PNG, JPEG, TIFF): apply the
    /// inverse sRGB transfer function to get linear light.
    Srgb,
    /// Scene-linear values as stored (OpenEXR and other floating-point files).
    Linear,
}

/// Decodes an image file with its format guessed from the content, or an error naming `path`.
fn decode_image(path: &Path) -> Result<(DynamicImage, Option<ImageFormat>)> {
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    let format = reader.format();
    let image = reader.decode().map_err(|e| match e {
        image::ImageError::IoError(e) => Error::io(path, e),
        other => Error::format(path, format!("corrupt or unsupported image: {other}")),
    })?;
    Ok((image, format))
}

/// Reads an RGB image as (H, W, 3) `f32`. 8- and 16-bit files (PNG, JPEG, TIFF) give their
/// sRGB-encoded values scaled to [0, 1] ([`PixelEncoding::Srgb`]); OpenEXR and float files give
/// linear values as stored ([`PixelEncoding::Linear`]). Alpha is dropped, grey is replicated.
/// Non-finite values are an error.
pub fn read_rgb_image(path: impl AsRef<Path>) -> Result<(Array3<f32>, PixelEncoding)> {
    let path = path.as_ref();
    let (image, format) = decode_image(path)?;
    let is_float = matches!(
        image,
        DynamicImage::ImageRgb32F(_) | DynamicImage::ImageRgba32F(_)
    );
    let encoding = if is_float || format == Some(ImageFormat::OpenExr) {
        PixelEncoding::Linear
    } else {
        PixelEncoding::Srgb
    };
    let rgb = image.to_rgb32f();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let pixels =
        Array3::from_shape_vec((h, w, 3), rgb.into_raw()).expect("decoder returns H*W*3 samples");
    if let Some(((y, x, c), v)) = pixels.indexed_iter().find(|(_, v)| !v.is_finite()) {
        return Err(Error::format(
            path,
            format!("non-finite value {v} at (y={y}, x={x}, channel {c})"),
        ));
    }
    Ok((pixels, encoding))
}

/// Reads a CFA drawn as a colour image: pure red (255, 0, 0), green (0, 255, 0) and blue
/// (0, 0, 255) pixels are those filters, white (255, 255, 255) pixels are W (clear), as in the
/// colour-SPAD calibration image of the paper's prototype (§6, Fig. 10). Returns the (H, W)
/// codes 0=R 1=G 2=B 3=W; any other colour is an error naming the file and the pixel.
pub fn read_cfa_png(path: impl AsRef<Path>) -> Result<Array2<u8>> {
    Ok(crate::cfa::load_png(path)?.codes().clone())
}
