//! The JavaScript library the pad's 3D view uses, taken from the npm registry at build time and
//! bundled into the binary (no CDN at run time: the pages work offline).
//!
//! `gl-matrix` (MIT): the 4 x 4 matrices of the view. The WebGL drawing itself is this crate's
//! own (`src/pad3d.js`). Fetched with `npm pack` (npm's cache makes later builds offline), else
//! with `curl` from the registry's tarball address (a machine without Node), or read from
//! `DPSA_GL_MATRIX_TGZ` (a tarball fetched beforehand); either way checked against the SHA-512
//! pinned here before a byte of it is used. Without the registry the build goes on without the
//! 3D view (a warning here, a sentence on the pad page), never with another file.

use sha2::{Digest, Sha512};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The package, its version and the SHA-512 of its tarball as the registry serves it
/// (`npm view gl-matrix@3.4.4 dist.integrity`, in hex).
const PACKAGE: &str = "gl-matrix";
const VERSION: &str = "3.4.4";
const SHA512: &str = "95ab529f20cdb7ff3361407a54827a3c28768c18c95fa8270eca0267b2f25bb1\
                      a4aab0f9d445b06bda82a068b18fc62a06d11340aff163b3a6a5317cc73d4375";
/// The files taken from it (inside the tarball's `package/`).
const FILES: [&str; 2] = ["gl-matrix-min.js", "LICENSE.md"];

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-env-changed=DPSA_GL_MATRIX_TGZ");
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    if let Err(why) = fetch(&out) {
        println!(
            "cargo::warning=the pad's 3D view is left out of this build: {PACKAGE} {VERSION} \
             could not be taken from the npm registry ({why}); install npm, or set \
             DPSA_GL_MATRIX_TGZ to its tarball"
        );
        for f in FILES {
            std::fs::write(out.join(f), "").expect("OUT_DIR is writable");
        }
    }
}

/// The tarball from `DPSA_GL_MATRIX_TGZ`, an earlier build's or `npm pack`, checked, its
/// files copied into `out`.
fn fetch(out: &Path) -> Result<(), String> {
    let name = format!("{PACKAGE}-{VERSION}.tgz");
    let tgz = match std::env::var_os("DPSA_GL_MATRIX_TGZ") {
        Some(p) => PathBuf::from(p),
        None => {
            let tgz = out.join(&name);
            if !checked(&tgz).unwrap_or(false) {
                let npm = Command::new("npm")
                    .args(["pack", &format!("{PACKAGE}@{VERSION}"), "--silent"])
                    .arg("--pack-destination")
                    .arg(out)
                    .stdout(std::process::Stdio::null())
                    .stderr(std::process::Stdio::null())
                    .status();
                if !npm.is_ok_and(|s| s.success()) {
                    let url = format!("https://registry.npmjs.org/{PACKAGE}/-/{name}");
                    let status = Command::new("curl")
                        .args(["-fsSL", "--max-time", "120", "-o"])
                        .arg(&tgz)
                        .arg(&url)
                        .status()
                        .map_err(|e| format!("neither npm nor curl: {e}"))?;
                    if !status.success() {
                        return Err(format!("npm pack failed, and curl {url}: {status}"));
                    }
                }
            }
            tgz
        }
    };
    if !checked(&tgz)? {
        return Err(format!(
            "{} is not the tarball pinned in build.rs (its SHA-512 differs)",
            tgz.display()
        ));
    }
    let dir = out.join("npm");
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let status = Command::new("tar")
        .arg("-xzf")
        .arg(&tgz)
        .arg("-C")
        .arg(&dir)
        .args(FILES.map(|f| format!("package/{f}")))
        .status()
        .map_err(|e| format!("tar: {e}"))?;
    if !status.success() {
        return Err(format!("tar: {status}"));
    }
    for f in FILES {
        std::fs::copy(dir.join("package").join(f), out.join(f)).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Whether `path` holds the pinned tarball.
fn checked(path: &Path) -> Result<bool, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let hex: String = Sha512::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    Ok(hex == SHA512.replace(' ', ""))
}
