//! Flash and RAM figures from the firmware ELF's sections.

use crate::{At, Result, SimError};
use serde::Serialize;

/// Largest firmware ELF read, bytes (64 MiB: the firmware with its debug information is a few
/// MB; the Cortex-M7's flash holds 2 MB).
pub const MAX_ELF_BYTES: u64 = 64 << 20;

/// Reads a firmware ELF: a regular file of at most [`MAX_ELF_BYTES`] (a FIFO or a device such
/// as `/dev/zero` is refused before it is opened), the error one sentence naming the file.
pub fn read_elf(path: &std::path::Path) -> Result<Vec<u8>> {
    Ok(crate::files::read_capped(
        path,
        MAX_ELF_BYTES,
        "firmware ELF",
    )?)
}

/// Sizes of the firmware image, bytes.
#[derive(Clone, Debug, Default, Serialize, PartialEq, Eq)]
pub struct ElfSizes {
    /// Bytes loaded into flash: every allocated section with contents (vector table, code,
    /// read-only data, the `.data` and `.itcm` load images).
    pub flash: u64,
    /// Static RAM: `.data + .bss + .uninit` (the `.state` region is not counted).
    pub static_ram: u64,
    /// Size of each section of interest.
    pub sections: Sections,
}

/// Section sizes, bytes (a section absent from the ELF is 0).
#[derive(Clone, Debug, Default, Serialize, PartialEq, Eq)]
pub struct Sections {
    /// `.vector_table`: the Cortex-M exception vectors.
    pub vector_table: u64,
    /// `.text`: code.
    pub text: u64,
    /// `.rodata`: read-only data.
    pub rodata: u64,
    /// `.data`: initialised statics (RAM; the load image is in flash).
    pub data: u64,
    /// `.bss`: zero-initialised statics.
    pub bss: u64,
    /// `.uninit`: statics left uninitialised at reset.
    pub uninit: u64,
    /// Hot code run from ITCM (its load image is in flash too).
    pub itcm: u64,
    /// NOLOAD region of the configuration-sized buffers (capacity reserved by the link).
    pub state: u64,
}

/// Section sizes of a firmware ELF.
pub fn elf_sizes(elf: &[u8]) -> Result<ElfSizes> {
    use object::{Object, ObjectSection, SectionFlags, SectionKind};
    let file = object::File::parse(elf)
        .map_err(|e| SimError::refused(e.to_string()))
        .at(|| "parsing the firmware ELF")?;
    let mut out = ElfSizes::default();
    for s in file.sections() {
        let name = s.name().unwrap_or("");
        let size = s.size();
        let alloc = match s.flags() {
            SectionFlags::Elf { sh_flags } => sh_flags & u64::from(object::elf::SHF_ALLOC) != 0,
            _ => false,
        };
        let nobits = matches!(
            s.kind(),
            SectionKind::UninitializedData | SectionKind::UninitializedTls
        ) || name == ".state";
        if alloc && !nobits {
            out.flash += size;
        }
        let is = |prefix: &str| name == prefix || name.starts_with(&format!("{prefix}."));
        let t = &mut out.sections;
        match () {
            _ if is(".vector_table") => t.vector_table += size,
            _ if is(".text") => t.text += size,
            _ if is(".rodata") => t.rodata += size,
            _ if is(".data") => t.data += size,
            _ if is(".bss") => t.bss += size,
            _ if is(".uninit") => t.uninit += size,
            _ if is(".itcm") => t.itcm += size,
            _ if is(".state") => t.state += size,
            _ => {}
        }
    }
    let t = &out.sections;
    out.static_ram = t.data + t.bss + t.uninit;
    if !(t.text > 0 || t.itcm > 0) {
        return Err(SimError::refused(
            "the ELF has no code sections: is it the firmware?",
        ));
    }
    Ok(out)
}
