//! Converts the published LPIPS-Alex v0.1 weights (float32 `.npz`, e.g.
//! `shared/data/lpips/lpips_alex_v0.1_oihw.npz`) to the embedded copy
//! `data/lpips/lpips_alex_v0.1_f16.npz`: every array rounded to the nearest IEEE binary16
//! (round-to-nearest-even, `half::f16::from_f32`) and stored as its uint16 bit pattern, same
//! names, same order, stored (uncompressed) zip entries dated 1980-01-01, so the output is
//! byte-for-byte reproducible.
//!
//! ```sh
//! cargo run --release -p quantacolor --example lpips_weights_f16 -- \
//!     ../shared/data/lpips/lpips_alex_v0.1_oihw.npz crates/quantacolor/data/lpips/lpips_alex_v0.1_f16.npz
//! ```

use std::fs::File;
use std::io::BufWriter;

use ndarray::ArrayD;
use ndarray_npy::{NpzReader, NpzWriter};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output] = args.as_slice() else {
        eprintln!("usage: lpips_weights_f16 IN_F32.npz OUT_F16.npz");
        std::process::exit(2);
    };
    let mut reader = NpzReader::new(File::open(input).map_err(|e| format!("{input}: {e}"))?)
        .map_err(|e| format!("{input}: {e}"))?;
    let tmp = format!("{output}.tmp");
    let mut writer = NpzWriter::new(BufWriter::new(File::create(&tmp)?));
    let mut worst = 0.0f32;
    for name in reader.names()? {
        let a: ArrayD<f32> = reader
            .by_name(&name)
            .map_err(|e| format!("{input}: {name}: {e}"))?;
        let bits = a.mapv(|v| half::f16::from_f32(v).to_bits());
        for (&v, &b) in a.iter().zip(bits.iter()) {
            let err = (half::f16::from_bits(b).to_f32() - v).abs() / v.abs().max(1e-30);
            worst = worst.max(if v.abs() < 6.2e-5 { 0.0 } else { err });
        }
        writer.add_array(name.as_str(), &bits)?;
        println!("{name}: {:?}", a.shape());
    }
    writer
        .finish()?
        .into_inner()
        .map_err(|e| e.into_error())?
        .sync_all()?;
    std::fs::rename(&tmp, output)?;
    println!("wrote {output}; worst relative rounding error of normal values {worst:.2e}");
    Ok(())
}
