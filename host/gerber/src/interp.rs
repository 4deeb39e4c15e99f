//! The graphics state machine: the parser's commands in file order -> the layer's objects
//! (flashes, strokes, regions), each a dark or clear shape in mm with its X2 attributes.

use super::lex::MARKER;
use super::object::{
    line_shape, num, vertex_count, ApertureShape, Class, Flat, Geom, Layer, MacroShape, Object,
    Stroke,
};
use super::shapes::{
    arc_band, arc_points, arc_segments, capsule, circle_points, dedup, eval_expr, polygon,
    recognise, rect_points, swept_rect, union_all, union_on, Exact, Prim,
};
use super::{GerberError, Limits, MAX_COORD_MM};
use crate::pads::Point;
use geo::{MultiPolygon, Polygon};
use gerber_parser::gerber_types::{
    Aperture, ApertureBlock, ApertureMacro, AttributeDeletionCriterion, AxisSelect, Command,
    CommentContent, CoordinateMode, CoordinateNumber, DCode, ExtendedCode, FileAttribute,
    FunctionCode, GCode, ImageMirroring, ImagePolarity, ImageRotation, InterpolationMode,
    MacroBoolean, MacroContent, MacroDecimal, MacroInteger, Mirroring, ObjectAttribute, Operation,
    Polarity, QuadrantMode, StandardComment, StepAndRepeat, ThermalPrimitive, Unit, ZeroOmission,
};
use std::collections::HashMap;
use std::sync::Arc;

/// What the interpreter made of the file.
pub(super) struct Interpreted {
    pub layer: Layer,
    pub units: &'static str,
    pub generator: Option<String>,
    pub warnings: Vec<String>,
    /// The file ended with M02.
    pub complete: bool,
}

/// The open `%SR` block.
struct StepRepeat {
    nx: u32,
    ny: u32,
    dx: f64,
    dy: f64,
    first: usize,
    line: usize,
}

/// The open region (`G36`): its contours so far.
struct Region {
    contours: Vec<Vec<Point>>,
    current: Vec<Point>,
    line: usize,
}

struct State {
    /// How much the layer may hold.
    limits: Limits,
    line: usize,
    /// mm per file unit.
    scale: Option<f64>,
    units: Option<&'static str>,
    format: Option<(ZeroOmission, CoordinateMode)>,
    incremental_words: bool,
    point: Point,
    mode: InterpolationMode,
    multi_quadrant: bool,
    dark: bool,
    mirroring: Mirroring,
    rotation_deg: f64,
    scaling: f64,
    macros: HashMap<String, ApertureMacro>,
    apertures: HashMap<i32, Arc<ApertureShape>>,
    current: Option<i32>,
    component: Option<Arc<str>>,
    pin: Option<Arc<str>>,
    /// The entries of `layer.attributes` and `layer.linears` for the current attributes
    /// and flash transform (`None`: changed since, a new entry is made on the next object).
    attributes_entry: Option<u32>,
    linear_entry: Option<u32>,
    region: Option<Region>,
    step: Option<StepRepeat>,
    layer: Layer,
    vertices: usize,
    generator: Option<String>,
    warnings: Vec<String>,
    unclosed_contours: usize,
    /// Region contours with no area (fewer than 3 distinct points, or all on one line): they
    /// draw nothing and are skipped with a warning (Altium writes such slivers).
    degenerate_contours: usize,
    zero_strokes: usize,
    ended: bool,
}

fn err(line: usize, message: impl Into<String>) -> GerberError {
    GerberError::Syntax {
        line,
        message: message.into(),
    }
}

fn unsupported(line: usize, what: impl Into<String>) -> GerberError {
    GerberError::Unsupported {
        line,
        what: what.into(),
    }
}

fn bbox_of(mp: &MultiPolygon<f64>) -> [f64; 4] {
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    for p in mp.iter() {
        for c in p.exterior().coords() {
            b = [b[0].min(c.x), b[1].min(c.y), b[2].max(c.x), b[3].max(c.y)];
        }
    }
    b
}

impl State {
    fn new(limits: Limits) -> State {
        State {
            limits,
            line: 0,
            scale: None,
            units: None,
            format: None,
            incremental_words: false,
            point: [0.0, 0.0],
            mode: InterpolationMode::Linear,
            multi_quadrant: true,
            dark: true,
            mirroring: Mirroring::None,
            rotation_deg: 0.0,
            scaling: 1.0,
            macros: HashMap::new(),
            apertures: HashMap::new(),
            current: None,
            component: None,
            pin: None,
            attributes_entry: Some(0),
            linear_entry: Some(0),
            region: None,
            step: None,
            layer: Layer::default(),
            vertices: 0,
            generator: None,
            warnings: Vec::new(),
            unclosed_contours: 0,
            degenerate_contours: 0,
            zero_strokes: 0,
            ended: false,
        }
    }

    fn scale(&self) -> Result<f64, GerberError> {
        self.scale.ok_or(GerberError::NoUnits { line: self.line })
    }

    /// A length of the file (aperture size, macro parameter) in mm, checked.
    fn length(&self, v: f64, what: &str) -> Result<f64, GerberError> {
        let mm = v * self.scale()?;
        if !mm.is_finite() || mm.abs() > MAX_COORD_MM {
            return Err(GerberError::OutOfRange {
                line: self.line,
                what: format!("{what} {v}"),
            });
        }
        Ok(mm)
    }

    fn coordinate(&self, c: Option<CoordinateNumber>, axis: usize) -> Result<f64, GerberError> {
        let Some(c) = c else {
            return Ok(self.point[axis]);
        };
        let (_, mode) = self
            .format
            .ok_or(GerberError::NoFormat { line: self.line })?;
        let v = f64::from(c) * self.scale()?;
        let v = if mode == CoordinateMode::Incremental || self.incremental_words {
            self.point[axis] + v
        } else {
            v
        };
        if !v.is_finite() || v.abs() > MAX_COORD_MM {
            return Err(GerberError::OutOfRange {
                line: self.line,
                what: format!("coordinate {:.3} mm", v),
            });
        }
        Ok(v)
    }

    fn offset(&self, c: Option<CoordinateNumber>) -> Result<f64, GerberError> {
        let v = c.map(f64::from).unwrap_or(0.0) * self.scale()?;
        if !v.is_finite() || v.abs() > MAX_COORD_MM {
            return Err(GerberError::OutOfRange {
                line: self.line,
                what: format!("arc offset {:.3} mm", v),
            });
        }
        Ok(v)
    }

    /// The flash transform of the current `%LM`, `%LR`, `%LS` (mirror, then rotate, then
    /// scale, about the flash point): the linear part of its [`Affine`].
    fn flash_transform(&self) -> [f64; 4] {
        let (mx, my) = match self.mirroring {
            Mirroring::None => (1.0, 1.0),
            Mirroring::X => (-1.0, 1.0),
            Mirroring::Y => (1.0, -1.0),
            Mirroring::XY => (-1.0, -1.0),
        };
        let (s, c) = self.rotation_deg.to_radians().sin_cos();
        let k = self.scaling;
        [k * c * mx, -k * s * my, k * s * mx, k * c * my]
    }

    /// The entry of `layer.linears` for the current flash transform.
    fn linear(&mut self) -> u32 {
        match self.linear_entry {
            Some(e) => e,
            None => {
                let e = self.layer.linears.len() as u32;
                let m = self.flash_transform();
                self.layer.linears.push(m);
                self.linear_entry = Some(e);
                e
            }
        }
    }

    fn aperture(&self) -> Result<&Arc<ApertureShape>, GerberError> {
        let code = self
            .current
            .ok_or_else(|| err(self.line, "no aperture selected"))?;
        self.apertures
            .get(&code)
            .ok_or(GerberError::UndefinedAperture {
                line: self.line,
                code,
            })
    }

    /// Counts `n` more polygon vertices held by the layer.
    fn count_vertices(&mut self, n: usize, line: usize) -> Result<(), GerberError> {
        self.vertices = self.vertices.saturating_add(n);
        if self.vertices > self.limits.vertices {
            return Err(GerberError::TooComplex {
                line,
                limit: self.limits.vertices,
            });
        }
        Ok(())
    }

    /// The vertices an object adds to the layer: a plain flash none (its pad is its exact
    /// outline, its polygon is made only where the merging needs it), any other flash its
    /// aperture's polygon (its pad will hold it), a stroke or region its polygon.
    fn held_vertices(o: &Object) -> usize {
        match &o.geom {
            Geom::Flash { ap, .. } if ap.exact().is_some() => 0,
            Geom::Flash { ap, .. } => vertex_count(&ap.polygon()),
            Geom::Line { ap, a, b } => vertex_count(&line_shape(ap, *a, *b)),
            Geom::Drawn { shape, .. } => shape.vertices(),
            Geom::Done => 0,
        }
    }

    /// Adds an object with the current polarity and attributes.
    fn push(&mut self, geom: Geom) -> Result<(), GerberError> {
        if self.layer.objects.len() >= self.limits.objects {
            return Err(GerberError::TooManyObjects {
                line: self.line,
                limit: self.limits.objects,
            });
        }
        let attributes = match self.attributes_entry {
            Some(e) => e,
            None => {
                let e = self.layer.attributes.len() as u32;
                self.layer
                    .attributes
                    .push((self.component.clone(), self.pin.clone()));
                self.attributes_entry = Some(e);
                e
            }
        };
        let bbox = match &geom {
            Geom::Drawn { shape, .. } => shape.bbox(),
            Geom::Flash { .. } | Geom::Line { .. } | Geom::Done => [0.0; 4],
        };
        self.layer.objects.push(Object {
            geom,
            bbox,
            dark: self.dark,
            attributes,
            copy: 0,
        });
        let i = self.layer.objects.len() - 1;
        if matches!(
            self.layer.objects[i].geom,
            Geom::Flash { .. } | Geom::Line { .. }
        ) {
            self.layer.objects[i].bbox = bbox_of(&self.layer.shape(i));
        }
        let n = Self::held_vertices(&self.layer.objects[i]);
        self.count_vertices(n, self.line)
    }

    fn command(&mut self, cmd: &Command) -> Result<(), GerberError> {
        if self.ended {
            return Ok(());
        }
        match cmd {
            Command::FunctionCode(FunctionCode::GCode(g)) => self.gcode(g),
            Command::FunctionCode(FunctionCode::DCode(DCode::SelectAperture(code))) => {
                if self.region.is_some() {
                    return Err(err(self.line, "aperture selected inside a region (G36)"));
                }
                self.current = Some(*code);
                Ok(())
            }
            Command::FunctionCode(FunctionCode::DCode(DCode::Operation(op))) => self.operation(op),
            Command::FunctionCode(FunctionCode::MCode(_)) => {
                self.ended = true;
                Ok(())
            }
            Command::ExtendedCode(x) => self.extended(x),
        }
    }

    fn gcode(&mut self, g: &GCode) -> Result<(), GerberError> {
        match g {
            GCode::InterpolationMode(m) => self.mode = *m,
            GCode::QuadrantMode(q) => self.multi_quadrant = *q == QuadrantMode::Multi,
            GCode::RegionMode(true) => {
                if self.region.is_some() {
                    return Err(err(self.line, "G36 inside a region"));
                }
                self.region = Some(Region {
                    contours: Vec::new(),
                    current: Vec::new(),
                    line: self.line,
                });
            }
            GCode::RegionMode(false) => {
                let Some(mut region) = self.region.take() else {
                    return Err(err(self.line, "G37 without G36"));
                };
                let last = std::mem::take(&mut region.current);
                region.contours.push(last);
                self.region_objects(region)?;
            }
            GCode::Comment(CommentContent::String(s)) => {
                let s = s.trim();
                if let Some(m) = s.strip_prefix(MARKER) {
                    if let Some(n) = m.strip_prefix("line:") {
                        self.line = n.parse().unwrap_or(self.line);
                    } else if m == "notation:incremental" {
                        self.incremental_words = true;
                    } else if m == "notation:absolute" {
                        self.incremental_words = false;
                    }
                }
            }
            GCode::Comment(CommentContent::Standard(sc)) => match sc {
                StandardComment::FileAttribute(fa) => self.file_attribute(fa),
                StandardComment::ObjectAttribute(oa) => self.object_attribute(oa),
                StandardComment::DeleteAttribute(d) => self.delete_attribute(d),
                StandardComment::ApertureAttribute(_) => {}
            },
            GCode::Unit(u) => self.set_units(*u)?,
            GCode::CoordinateMode(m) => {
                self.incremental_words = *m == CoordinateMode::Incremental;
            }
            GCode::SelectAperture => {}
        }
        Ok(())
    }

    fn set_units(&mut self, u: Unit) -> Result<(), GerberError> {
        let (scale, name) = match u {
            Unit::Millimeters => (1.0, "mm"),
            Unit::Inches => (25.4, "inch"),
        };
        if self.units.is_some_and(|n| n != name) {
            return Err(err(self.line, "units changed in the middle of the file"));
        }
        self.scale = Some(scale);
        self.units = Some(name);
        Ok(())
    }

    fn file_attribute(&mut self, fa: &FileAttribute) {
        if let FileAttribute::GenerationSoftware(g) = fa {
            let mut s = format!("{},{}", g.vendor, g.application);
            if let Some(v) = &g.version {
                s.push(',');
                s.push_str(v);
            }
            self.generator = Some(s);
        }
    }

    fn object_attribute(&mut self, oa: &ObjectAttribute) {
        match oa {
            ObjectAttribute::Component(c) => self.component = Some(Arc::from(c.as_str())),
            ObjectAttribute::Pin(p) => {
                self.component = Some(Arc::from(p.refdes.as_str()));
                self.pin = Some(Arc::from(p.name.as_str()));
            }
            _ => return,
        }
        self.attributes_entry = None;
    }

    fn delete_attribute(&mut self, d: &AttributeDeletionCriterion) {
        match d {
            AttributeDeletionCriterion::AllApertureAndObjectAttributes => {
                self.component = None;
                self.pin = None;
            }
            AttributeDeletionCriterion::SingleObjectAttribute(name) => match name.as_str() {
                ".C" | "C" => self.component = None,
                ".P" | "P" => self.pin = None,
                _ => {}
            },
            AttributeDeletionCriterion::SingleApertureAttribute(_) => return,
        }
        self.attributes_entry = None;
    }

    fn extended(&mut self, x: &ExtendedCode) -> Result<(), GerberError> {
        match x {
            ExtendedCode::CoordinateFormat(f) => {
                self.format = Some((f.zero_omission, f.coordinate_mode));
            }
            ExtendedCode::Unit(u) => self.set_units(*u)?,
            ExtendedCode::ApertureMacro(m) => {
                self.macros.insert(m.name.clone(), m.clone());
            }
            ExtendedCode::ApertureDefinition(d) => {
                if self.apertures.contains_key(&d.code) {
                    return Err(err(
                        self.line,
                        format!("aperture D{} is defined twice", d.code),
                    ));
                }
                let shape = self.define(&d.aperture)?;
                if let ApertureShape::Macro(m) = &shape {
                    self.count_vertices(vertex_count(&m.shape), self.line)?;
                }
                self.apertures.insert(d.code, Arc::new(shape));
            }
            ExtendedCode::LoadPolarity(p) => self.dark = *p == Polarity::Dark,
            ExtendedCode::LoadMirroring(m) => {
                self.mirroring = *m;
                self.linear_entry = None;
            }
            ExtendedCode::LoadRotation(r) => {
                if !r.rotation.is_finite() {
                    return Err(err(self.line, "rotation is not a number"));
                }
                self.rotation_deg = r.rotation;
                self.linear_entry = None;
            }
            ExtendedCode::LoadScaling(s) => {
                if !(s.scale.is_finite() && s.scale > 0.0 && s.scale < 1e6) {
                    return Err(GerberError::OutOfRange {
                        line: self.line,
                        what: format!("scaling {}", s.scale),
                    });
                }
                self.scaling = s.scale;
                self.linear_entry = None;
            }
            ExtendedCode::StepAndRepeat(sr) => self.step_repeat(sr)?,
            ExtendedCode::ApertureBlock(ApertureBlock::Open { .. }) => {
                return Err(unsupported(self.line, "block apertures (%AB)"));
            }
            ExtendedCode::ApertureBlock(ApertureBlock::Close) => {
                return Err(unsupported(self.line, "block apertures (%AB)"));
            }
            ExtendedCode::FileAttribute(fa) => self.file_attribute(fa),
            ExtendedCode::ObjectAttribute(oa) => self.object_attribute(oa),
            ExtendedCode::DeleteAttribute(d) => self.delete_attribute(d),
            ExtendedCode::ApertureAttribute(_) | ExtendedCode::ImageName(_) => {}
            ExtendedCode::ImagePolarity(p) => {
                if *p == ImagePolarity::Negative {
                    return Err(unsupported(self.line, "negative image polarity (%IPNEG)"));
                }
            }
            ExtendedCode::MirrorImage(m) => {
                if *m != ImageMirroring::None {
                    return Err(unsupported(self.line, "image mirroring (%MI)"));
                }
            }
            ExtendedCode::RotateImage(r) => {
                if *r != ImageRotation::None {
                    return Err(unsupported(self.line, "image rotation (%IR)"));
                }
            }
            ExtendedCode::OffsetImage(o) => {
                if o.a != 0.0 || o.b != 0.0 {
                    return Err(unsupported(self.line, "image offset (%OF)"));
                }
            }
            ExtendedCode::ScaleImage(s) => {
                if s.a != 1.0 || s.b != 1.0 {
                    return Err(unsupported(self.line, "image scaling (%SF)"));
                }
            }
            ExtendedCode::AxisSelect(a) => {
                if *a != AxisSelect::AXBY {
                    return Err(unsupported(self.line, "axis swap (%ASAYBX)"));
                }
            }
        }
        Ok(())
    }

    fn step_repeat(&mut self, sr: &StepAndRepeat) -> Result<(), GerberError> {
        // Close any open block first (an open %SR also closes the previous one).
        if let Some(open) = self.step.take() {
            self.expand(open)?;
        }
        if let StepAndRepeat::Open {
            repeat_x,
            repeat_y,
            distance_x,
            distance_y,
        } = *sr
        {
            if repeat_x == 0 || repeat_y == 0 {
                return Err(err(self.line, "step and repeat with 0 repeats"));
            }
            let copies = u64::from(repeat_x) * u64::from(repeat_y);
            if copies > self.limits.objects as u64 {
                return Err(GerberError::TooManyObjects {
                    line: self.line,
                    limit: self.limits.objects,
                });
            }
            let (dx, dy) = (
                self.length(distance_x, "step distance")?,
                self.length(distance_y, "step distance")?,
            );
            self.step = Some(StepRepeat {
                nx: repeat_x,
                ny: repeat_y,
                dx,
                dy,
                first: self.layer.objects.len(),
                line: self.line,
            });
        }
        Ok(())
    }

    /// Replicates the objects of a closed `%SR` block: the copies share the block's
    /// apertures and polygons, each with its offset.
    fn expand(&mut self, sr: StepRepeat) -> Result<(), GerberError> {
        let block: Vec<Object> = self.layer.objects[sr.first..].to_vec();
        let copies = (sr.nx as usize) * (sr.ny as usize);
        let total = sr.first + block.len() * copies;
        if total > self.limits.objects {
            return Err(GerberError::TooManyObjects {
                line: sr.line,
                limit: self.limits.objects,
            });
        }
        let verts: usize = block.iter().map(Self::held_vertices).sum();
        self.count_vertices(verts.saturating_mul(copies.saturating_sub(1)), sr.line)?;
        self.layer.objects.truncate(sr.first);
        self.layer.objects.reserve(block.len() * copies);
        for j in 0..sr.ny {
            for i in 0..sr.nx {
                let t = [f64::from(i) * sr.dx, f64::from(j) * sr.dy];
                let copy = if i != 0 || j != 0 {
                    self.layer.shifts.push(t);
                    (self.layer.shifts.len() - 1) as u32
                } else {
                    0
                };
                for o in &block {
                    let mut c = o.clone();
                    if copy != 0 {
                        c.copy = copy;
                        c.bbox = [
                            o.bbox[0] + t[0],
                            o.bbox[1] + t[1],
                            o.bbox[2] + t[0],
                            o.bbox[3] + t[1],
                        ];
                        if c.bbox.iter().any(|v| v.abs() > MAX_COORD_MM) {
                            return Err(GerberError::OutOfRange {
                                line: sr.line,
                                what: "step and repeat beyond 10 m".into(),
                            });
                        }
                    }
                    self.layer.objects.push(c);
                }
            }
        }
        Ok(())
    }

    /// The shape of an aperture definition, about its origin, mm.
    fn define(&self, ap: &Aperture) -> Result<ApertureShape, GerberError> {
        // The round hole of a standard aperture: it must lie inside the aperture (`inside`
        // is the diameter of the largest centred disc the aperture holds), else the file
        // describes no shape and is refused.
        let hole = |h: Option<f64>, inside: f64| -> Result<f64, GerberError> {
            let Some(d) = h else {
                return Ok(0.0);
            };
            let mm = self.length(d, "hole")?;
            if mm < 0.0 {
                return Err(GerberError::OutOfRange {
                    line: self.line,
                    what: format!("negative hole {d}"),
                });
            }
            if mm == 0.0 {
                return Ok(0.0);
            }
            if mm >= inside {
                return Err(err(
                    self.line,
                    format!(
                        "aperture hole {d} is not inside its aperture (at most {} wide there)",
                        num(inside / self.scale()?)
                    ),
                ));
            }
            Ok(mm)
        };
        let positive = |v: f64, what: &str| -> Result<f64, GerberError> {
            let mm = self.length(v, what)?;
            if mm < 0.0 {
                return Err(GerberError::OutOfRange {
                    line: self.line,
                    what: format!("negative {what} {v}"),
                });
            }
            Ok(mm)
        };
        Ok(match ap {
            Aperture::Circle(c) => {
                let d = positive(c.diameter, "diameter")?;
                let hole = hole(c.hole_diameter, d)?;
                ApertureShape::Circle { d, hole }
            }
            Aperture::Rectangle(r) | Aperture::Obround(r) => {
                let (w, h) = (positive(r.x, "width")?, positive(r.y, "height")?);
                let hole = hole(r.hole_diameter, w.min(h))?;
                ApertureShape::Rect {
                    w,
                    h,
                    obround: matches!(ap, Aperture::Obround(_)),
                    hole,
                }
            }
            Aperture::Polygon(p) => {
                let d = positive(p.diameter, "diameter")?;
                let n = p.vertices;
                if !(3..=12).contains(&n) {
                    return Err(err(
                        self.line,
                        format!("polygon aperture with {n} vertices"),
                    ));
                }
                let rot = p.rotation.unwrap_or(0.0);
                if !rot.is_finite() {
                    return Err(GerberError::OutOfRange {
                        line: self.line,
                        what: format!("polygon rotation {rot}"),
                    });
                }
                // The inscribed circle: the largest hole the polygon holds.
                let inside = d * (std::f64::consts::PI / f64::from(n)).cos();
                ApertureShape::Regular {
                    d,
                    n: u32::from(n),
                    rot,
                    hole: hole(p.hole_diameter, inside)?,
                }
            }
            Aperture::Macro(name, params) => self.define_macro(name, params.as_deref())?,
        })
    }

    fn define_macro(
        &self,
        name: &str,
        params: Option<&[MacroDecimal]>,
    ) -> Result<ApertureShape, GerberError> {
        let m = self
            .macros
            .get(name)
            .ok_or_else(|| err(self.line, format!("aperture macro {name:?} is not defined")))?;
        let mut vars = macro_params(params, self.line)?;
        let eval = MacroEval {
            name,
            line: self.line,
            scale: self.scale()?,
        };
        let prims = eval.primitives(&m.content, &mut vars)?;
        let shape = expose(&prims);
        let all_on = prims.iter().all(|(on, _)| *on);
        let only: Vec<Prim> = prims.into_iter().map(|(_, p)| p).collect();
        let exact = if all_on {
            recognise(&only, super::shapes::area(&shape))
        } else {
            None
        };
        Ok(ApertureShape::Macro(Box::new(MacroShape {
            shape,
            exact,
            class: macro_class(name, exact),
        })))
    }

    fn operation(&mut self, op: &Operation) -> Result<(), GerberError> {
        match op {
            Operation::Move(c) => {
                let p = self.target(c.as_ref().map(|c| (c.x, c.y)))?;
                if let Some(region) = &mut self.region {
                    let cur = std::mem::take(&mut region.current);
                    if !cur.is_empty() {
                        region.contours.push(cur);
                    }
                    region.current.push(p);
                }
                self.point = p;
            }
            Operation::Flash(c) => {
                if self.region.is_some() {
                    return Err(err(self.line, "flash (D03) inside a region (G36)"));
                }
                let p = self.target(c.as_ref().map(|c| (c.x, c.y)))?;
                self.point = p;
                self.flash(p)?;
            }
            Operation::Interpolate(c, off) => {
                let p = self.target(c.as_ref().map(|c| (c.x, c.y)))?;
                let start = self.point;
                let mut arc = None;
                let path: Vec<Point> = match self.mode {
                    InterpolationMode::Linear => vec![p],
                    m => {
                        let (i, j) = match off {
                            Some(o) => (self.offset(o.x)?, self.offset(o.y)?),
                            None => (0.0, 0.0),
                        };
                        let cw = m == InterpolationMode::ClockwiseCircular;
                        let centre = if self.multi_quadrant {
                            [start[0] + i, start[1] + j]
                        } else {
                            single_quadrant_centre(start, p, i.abs(), j.abs(), cw)
                        };
                        // The end must lie on the start's circle (files round the two
                        // radii differently by a few um): an "arc" from its own centre to
                        // a point a metre away is a corrupt file, not a spiral to draw.
                        let (r0, r1) = (
                            (start[0] - centre[0]).hypot(start[1] - centre[1]),
                            (p[0] - centre[0]).hypot(p[1] - centre[1]),
                        );
                        if (r1 - r0).abs() > ARC_RADII_MM + ARC_RADII_SHARE * r0.max(r1) {
                            return Err(err(
                                self.line,
                                format!(
                                    "arc: its start is {r0:.4} mm from its centre, its end \
                                     {r1:.4} mm: not one circle (at most {ARC_RADII_MM} mm + \
                                     {}% apart)",
                                    ARC_RADII_SHARE * 100.0
                                ),
                            ));
                        }
                        arc = Some((centre, cw));
                        arc_points(start, p, centre, cw)
                    }
                };
                if let Some(region) = &mut self.region {
                    if region.current.is_empty() {
                        region.current.push(start);
                    }
                    region.current.extend(path);
                } else if let Some((centre, cw)) = arc {
                    self.stroke_arc(start, p, centre, cw, &path)?;
                } else {
                    self.stroke(start, &path)?;
                }
                self.point = p;
            }
        }
        Ok(())
    }

    fn target(
        &self,
        c: Option<(Option<CoordinateNumber>, Option<CoordinateNumber>)>,
    ) -> Result<Point, GerberError> {
        match c {
            None => Ok(self.point),
            Some((x, y)) => Ok([self.coordinate(x, 0)?, self.coordinate(y, 1)?]),
        }
    }

    fn flash(&mut self, at: Point) -> Result<(), GerberError> {
        let ap = Arc::clone(self.aperture()?);
        if ap.is_empty() {
            return Ok(());
        }
        let linear = self.linear();
        self.push(Geom::Flash { ap, at, linear })
    }

    /// A stroke along an arc: with a circular aperture, the band the disc sweeps (an annular
    /// sector and the discs at its ends, [`arc_band`]), else the union of the chords' pieces.
    fn stroke_arc(
        &mut self,
        start: Point,
        end: Point,
        centre: Point,
        cw: bool,
        path: &[Point],
    ) -> Result<(), GerberError> {
        let ap = Arc::clone(self.aperture()?);
        let Stroke::Circle(d) = ap.stroke() else {
            return self.stroke(start, path);
        };
        if d <= 0.0 {
            self.zero_strokes += 1;
            return Ok(());
        }
        let Some(pieces) = arc_band(start, end, centre, cw, d) else {
            return self.stroke(start, path);
        };
        let shape = union_all(&pieces);
        if shape.0.is_empty() {
            return Ok(());
        }
        self.push(Geom::Drawn {
            shape: Flat::new(&shape),
            class: Class::Stroke(ap),
        })
    }

    fn stroke(&mut self, start: Point, path: &[Point]) -> Result<(), GerberError> {
        let ap = Arc::clone(self.aperture()?);
        let stroke = ap.stroke();
        // What the pieces will hold before their union, checked before any is made: an
        // absurd aperture swept along a long arc (a 9 m disc along 4096 chords) is refused
        // here, not after gigabytes.
        let per_piece = match stroke {
            Stroke::Circle(d) if d > 0.0 => {
                2 * (arc_segments(d / 2.0, std::f64::consts::PI).max(4) + 1)
            }
            _ => 8,
        };
        let pieces_vertices = per_piece.saturating_mul(path.len());
        if pieces_vertices > self.limits.stroke_vertices {
            return Err(GerberError::StrokeTooComplex {
                line: self.line,
                aperture: ap.class(),
                vertices: pieces_vertices,
                limit: self.limits.stroke_vertices,
            });
        }
        if let ([b], Stroke::Circle(_) | Stroke::Rect(..)) = (path, stroke) {
            // A straight stroke: its polygon is made where it is needed.
            if matches!(stroke, Stroke::Circle(d) if d <= 0.0) {
                self.zero_strokes += 1;
                return Ok(());
            }
            let b = *b;
            return self.push(Geom::Line { ap, a: start, b });
        }
        let mut pieces = Vec::with_capacity(path.len());
        let mut a = start;
        for &b in path {
            let pts = match stroke {
                Stroke::Circle(d) if d > 0.0 => capsule(a, b, d),
                Stroke::Circle(_) => {
                    self.zero_strokes += 1;
                    return Ok(());
                }
                Stroke::Rect(w, h) => swept_rect(a, b, w, h),
                Stroke::None => {
                    return Err(unsupported(
                        self.line,
                        format!(
                            "drawing (D01) with aperture {:?}: only C and R may draw",
                            ap.class()
                        ),
                    ))
                }
            };
            pieces.push(polygon(&pts, &[]));
            a = b;
        }
        let shape = if pieces.len() == 1 {
            MultiPolygon::new(pieces)
        } else {
            union_all(&pieces)
        };
        if shape.0.is_empty() {
            return Ok(());
        }
        self.push(Geom::Drawn {
            shape: Flat::new(&shape),
            class: Class::Stroke(ap),
        })
    }

    fn region_objects(&mut self, region: Region) -> Result<(), GerberError> {
        let line = self.line;
        self.line = region.line;
        for contour in region.contours {
            // A start point with no segment after it (Altium ends every region with a bare
            // `D02*` before `G37*`) draws nothing: it is not a contour.
            if contour.len() < 2 {
                continue;
            }
            let (first, last) = (contour[0], contour[contour.len() - 1]);
            if (first[0] - last[0]).abs() > 1e-6 || (first[1] - last[1]).abs() > 1e-6 {
                self.unclosed_contours += 1;
            }
            let pts = dedup(contour);
            let shape = if pts.len() < 3 {
                MultiPolygon::new(Vec::new())
            } else {
                union_all(&[polygon(&pts, &[])])
            };
            if shape.0.is_empty() {
                self.degenerate_contours += 1;
                continue;
            }
            self.push(Geom::Drawn {
                shape: Flat::new(&shape),
                class: Class::Region,
            })?;
        }
        self.line = line;
        Ok(())
    }
}

const TAU_DEG: f64 = 360.0;

/// Most the radii of an arc's start and end may differ: this, plus [`ARC_RADII_SHARE`] of
/// the radius, mm (files round them differently; more is not one circle).
pub(super) const ARC_RADII_MM: f64 = 0.05;
/// See [`ARC_RADII_MM`].
pub(super) const ARC_RADII_SHARE: f64 = 0.02;

/// The centre of a single-quadrant (`G74`) arc: the signs of `i`, `j` are not given; the
/// one whose arc is at most 90 degrees and whose radii agree best wins.
fn single_quadrant_centre(start: Point, end: Point, i: f64, j: f64, cw: bool) -> Point {
    let mut best = ([start[0] + i, start[1] + j], f64::INFINITY);
    for (si, sj) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        let c = [start[0] + si * i, start[1] + sj * j];
        let a0 = (start[1] - c[1]).atan2(start[0] - c[0]);
        let a1 = (end[1] - c[1]).atan2(end[0] - c[0]);
        let sweep = if cw { a0 - a1 } else { a1 - a0 }.rem_euclid(std::f64::consts::TAU);
        if sweep > std::f64::consts::FRAC_PI_2 + 1e-6 {
            continue;
        }
        let dr =
            ((start[0] - c[0]).hypot(start[1] - c[1]) - (end[0] - c[0]).hypot(end[1] - c[1])).abs();
        if dr < best.1 {
            best = (c, dr);
        }
    }
    best.0
}

/// The graphics state fed with the parser's commands a chunk at a time.
pub(super) struct Interpreter {
    st: State,
}

impl Interpreter {
    pub fn new(limits: Limits) -> Interpreter {
        Interpreter {
            st: State::new(limits),
        }
    }

    /// Runs a chunk of commands (those after `M02` are ignored).
    pub fn feed(&mut self, commands: &[Command]) -> Result<(), GerberError> {
        for cmd in commands {
            if self.st.ended {
                break;
            }
            self.st.command(cmd)?;
        }
        Ok(())
    }

    /// Notes a warning of the pre-processing.
    pub fn warn(&mut self, warnings: impl IntoIterator<Item = String>) {
        self.st.warnings.extend(warnings);
    }

    /// The end of the file: open blocks, the end-of-file statement, the warnings.
    pub fn finish(self) -> Result<Interpreted, GerberError> {
        finish(self.st)
    }
}

fn finish(mut st: State) -> Result<Interpreted, GerberError> {
    if let Some(region) = &st.region {
        return Err(GerberError::UnclosedRegion { line: region.line });
    }
    if let Some(open) = st.step.take() {
        if st.ended {
            st.warnings.push(format!(
                "line {}: step and repeat not closed before M02",
                open.line
            ));
            st.expand(open)?;
        } else {
            return Err(GerberError::Truncated {
                line: open.line,
                what: "step and repeat (%SR) never closed".into(),
            });
        }
    }
    if !st.ended {
        st.warnings
            .push("no M02 at the end: the file may be truncated (its geometry is complete)".into());
    }
    if st.units.is_none() {
        return Err(GerberError::NoUnits { line: st.line });
    }
    if st.unclosed_contours > 0 {
        st.warnings.push(format!(
            "{} region contour(s) not closed by the file; closed with a straight edge",
            st.unclosed_contours
        ));
    }
    if st.degenerate_contours > 0 {
        st.warnings.push(format!(
            "{} region contour(s) with no area (fewer than 3 distinct points or all on one line) ignored",
            st.degenerate_contours
        ));
    }
    if st.zero_strokes > 0 {
        st.warnings.push(format!(
            "{} stroke(s) with a zero-size aperture ignored (they have no area)",
            st.zero_strokes
        ));
    }
    Ok(Interpreted {
        layer: st.layer,
        units: st.units.unwrap_or("mm"),
        generator: st.generator,
        warnings: st.warnings,
        complete: st.ended,
    })
}

/// An aperture's parameters as the macro's variables `$1`, `$2`, ... (numbers only).
fn macro_params(
    params: Option<&[MacroDecimal]>,
    line: usize,
) -> Result<HashMap<u32, f64>, GerberError> {
    let mut vars: HashMap<u32, f64> = HashMap::new();
    for (i, p) in params.unwrap_or(&[]).iter().enumerate() {
        let v = match p {
            MacroDecimal::Value(v) => *v,
            MacroDecimal::Variable(_) | MacroDecimal::Expression(_) => {
                return Err(err(line, "aperture parameters must be numbers"));
            }
        };
        vars.insert(i as u32 + 1, v);
    }
    Ok(vars)
}

/// `p` turned by `deg` degrees about the origin.
fn rotate(p: Point, deg: f64) -> Point {
    let (s, c) = deg.to_radians().sin_cos();
    [c * p[0] - s * p[1], s * p[0] + c * p[1]]
}

/// Evaluates the primitives of macro `name` (instantiated at `line`, file units times
/// `scale` = mm).
struct MacroEval<'a> {
    name: &'a str,
    line: usize,
    scale: f64,
}

impl MacroEval<'_> {
    /// A decimal value, finite and inside the coordinate range.
    fn dec(&self, d: &MacroDecimal, vars: &HashMap<u32, f64>) -> Result<f64, GerberError> {
        let (name, line) = (self.name, self.line);
        let v = match d {
            MacroDecimal::Value(v) => *v,
            MacroDecimal::Variable(n) => vars.get(n).copied().unwrap_or(0.0),
            MacroDecimal::Expression(e) => {
                eval_expr(e, vars).map_err(|m| err(line, format!("macro {name}: {m} in {e:?}")))?
            }
        };
        if !v.is_finite() || v.abs() * self.scale > MAX_COORD_MM {
            return Err(GerberError::OutOfRange {
                line,
                what: format!("macro {name} value {v}"),
            });
        }
        Ok(v)
    }

    /// An exposure (non-zero: on).
    fn boolean(&self, b: &MacroBoolean, vars: &HashMap<u32, f64>) -> Result<bool, GerberError> {
        let (name, line) = (self.name, self.line);
        Ok(match b {
            MacroBoolean::Value(v) => *v,
            MacroBoolean::Variable(n) => vars.get(n).copied().unwrap_or(0.0) != 0.0,
            MacroBoolean::Expression(e) => {
                eval_expr(e, vars).map_err(|m| err(line, format!("macro {name}: {m}")))? != 0.0
            }
        })
    }

    /// A count in `0..=10^6`, rounded.
    fn integer(&self, i: &MacroInteger, vars: &HashMap<u32, f64>) -> Result<u32, GerberError> {
        let (name, line) = (self.name, self.line);
        let v = match i {
            MacroInteger::Value(v) => f64::from(*v),
            MacroInteger::Variable(n) => vars.get(n).copied().unwrap_or(0.0),
            MacroInteger::Expression(e) => {
                eval_expr(e, vars).map_err(|m| err(line, format!("macro {name}: {m}")))?
            }
        };
        if !(0.0..=1e6).contains(&v) {
            return Err(err(line, format!("macro {name}: bad count {v}")));
        }
        Ok(v.round() as u32)
    }

    /// A point of two decimals.
    fn point(
        &self,
        p: &(MacroDecimal, MacroDecimal),
        vars: &HashMap<u32, f64>,
    ) -> Result<Point, GerberError> {
        Ok([self.dec(&p.0, vars)?, self.dec(&p.1, vars)?])
    }

    /// The macro's body in order: variable definitions update `vars`, primitives become
    /// (exposure, primitive) in mm with the macro rotation applied.
    fn primitives(
        &self,
        content: &[MacroContent],
        vars: &mut HashMap<u32, f64>,
    ) -> Result<Vec<(bool, Prim)>, GerberError> {
        let (name, line) = (self.name, self.line);
        let mut prims: Vec<(bool, Prim)> = Vec::new();
        for content in content {
            let prim = match content {
                MacroContent::Comment(_) => continue,
                MacroContent::VariableDefinition(v) => {
                    let value = eval_expr(&v.expression, vars)
                        .map_err(|e| err(line, format!("macro {name}: {e}")))?;
                    vars.insert(v.number, value);
                    continue;
                }
                MacroContent::Thermal(t) => {
                    for poly in self.thermal(t, vars)? {
                        prims.push((true, poly));
                    }
                    continue;
                }
                MacroContent::Moire(_) => {
                    return Err(unsupported(
                        line,
                        format!("moire primitive in macro {name}"),
                    ));
                }
                other => self.primitive(other, vars)?,
            };
            prims.push(prim);
        }
        Ok(prims)
    }

    /// One circle, vector line, centre line, outline or polygon primitive.
    fn primitive(
        &self,
        content: &MacroContent,
        vars: &HashMap<u32, f64>,
    ) -> Result<(bool, Prim), GerberError> {
        let (name, line, scale) = (self.name, self.line, self.scale);
        Ok(match content {
            MacroContent::Circle(c) => {
                let rot = c
                    .angle
                    .as_ref()
                    .map(|a| self.dec(a, vars))
                    .transpose()?
                    .unwrap_or(0.0);
                let centre = rotate(self.point(&c.center, vars)?, rot);
                (
                    self.boolean(&c.exposure, vars)?,
                    Prim::Circle {
                        c: [centre[0] * scale, centre[1] * scale],
                        d: self.dec(&c.diameter, vars)?.abs() * scale,
                    },
                )
            }
            MacroContent::VectorLine(v) => {
                let rot = self.dec(&v.angle, vars)?;
                let (a, b) = (self.point(&v.start, vars)?, self.point(&v.end, vars)?);
                let w = self.dec(&v.width, vars)?.abs();
                let len = (b[0] - a[0]).hypot(b[1] - a[1]);
                let dir = (b[1] - a[1]).atan2(b[0] - a[0]).to_degrees();
                let mid = rotate([(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0], rot);
                (
                    self.boolean(&v.exposure, vars)?,
                    Prim::Rect {
                        c: [mid[0] * scale, mid[1] * scale],
                        w: len * scale,
                        h: w * scale,
                        rot: dir + rot,
                    },
                )
            }
            MacroContent::CenterLine(c) => {
                let rot = self.dec(&c.angle, vars)?;
                let centre = rotate(self.point(&c.center, vars)?, rot);
                (
                    self.boolean(&c.exposure, vars)?,
                    Prim::Rect {
                        c: [centre[0] * scale, centre[1] * scale],
                        w: self.dec(&c.dimensions.0, vars)?.abs() * scale,
                        h: self.dec(&c.dimensions.1, vars)?.abs() * scale,
                        rot,
                    },
                )
            }
            MacroContent::Outline(o) => {
                let rot = self.dec(&o.angle, vars)?;
                let mut pts = Vec::with_capacity(o.points.len());
                for (x, y) in &o.points {
                    let p = rotate([self.dec(x, vars)?, self.dec(y, vars)?], rot);
                    pts.push([p[0] * scale, p[1] * scale]);
                }
                let pts = dedup(pts);
                if pts.len() < 3 {
                    return Err(err(line, format!("macro {name}: outline with < 3 points")));
                }
                (self.boolean(&o.exposure, vars)?, Prim::Poly(pts))
            }
            MacroContent::Polygon(p) => {
                let rot = self.dec(&p.angle, vars)?;
                let n = self.integer(&p.vertices, vars)?;
                if !(3..=12).contains(&n) {
                    return Err(err(
                        line,
                        format!("macro {name}: polygon with {n} vertices"),
                    ));
                }
                let c = self.point(&p.center, vars)?;
                let d = self.dec(&p.diameter, vars)?.abs();
                let pts = (0..n)
                    .map(|i| {
                        let a = TAU_DEG * f64::from(i) / f64::from(n);
                        let q = [
                            c[0] + d / 2.0 * a.to_radians().cos(),
                            c[1] + d / 2.0 * a.to_radians().sin(),
                        ];
                        let q = rotate(q, rot);
                        [q[0] * scale, q[1] * scale]
                    })
                    .collect();
                (self.boolean(&p.exposure, vars)?, Prim::Poly(pts))
            }
            _ => unreachable!("primitives() handles the other macro contents"),
        })
    }

    /// A thermal: a ring cut by a cross of `gap` width; its pieces as polygons (always on).
    fn thermal(
        &self,
        t: &ThermalPrimitive,
        vars: &HashMap<u32, f64>,
    ) -> Result<Vec<Prim>, GerberError> {
        let scale = self.scale;
        let rot = self.dec(&t.angle, vars)?;
        let c = self.point(&t.center, vars)?;
        let (od, id, gap) = (
            self.dec(&t.outer_diameter, vars)?.abs(),
            self.dec(&t.inner_diameter, vars)?.abs(),
            self.dec(&t.gap, vars)?.abs(),
        );
        let ring = polygon(&circle_points(c, od), &[circle_points(c, id)]);
        let cross = MultiPolygon::new(vec![
            polygon(&rect_points(c, od * 2.0, gap, 0.0), &[]),
            polygon(&rect_points(c, gap, od * 2.0, 0.0), &[]),
        ]);
        let pieces = crate::overlay::difference(&MultiPolygon::new(vec![ring]), &cross, None);
        Ok(pieces
            .iter()
            .map(|piece| {
                let pts: Vec<Point> = piece
                    .exterior()
                    .coords()
                    .map(|q| {
                        let r = rotate([q.x, q.y], rot);
                        [r[0] * scale, r[1] * scale]
                    })
                    .collect();
                Prim::Poly(dedup(pts))
            })
            .collect())
    }
}

/// Sequential exposure of a macro's primitives: dark runs are unioned at once, clear ones cut.
fn expose(prims: &[(bool, Prim)]) -> MultiPolygon<f64> {
    let polys: Vec<Polygon<f64>> = prims
        .iter()
        .map(|(_, p)| polygon(&p.points(), &[]))
        .collect();
    // One grid for every step: the cuts and unions meet on it.
    let grid = crate::overlay::Grid::of(&polys);
    let grid = grid.as_ref();
    let mut shape = MultiPolygon::<f64>::new(vec![]);
    let mut run: Vec<Polygon<f64>> = Vec::new();
    for ((on, _), poly) in prims.iter().zip(polys) {
        if *on {
            run.push(poly);
        } else {
            if !run.is_empty() {
                run.append(&mut shape.0);
                shape = union_on(&run, grid);
                run.clear();
            }
            shape = crate::overlay::difference(&shape, &MultiPolygon::new(vec![poly]), grid);
        }
    }
    if !run.is_empty() {
        run.append(&mut shape.0);
        shape = union_on(&run, grid);
    }
    shape
}

/// The aperture class of a macro instance: its name, and the size when it is exactly a
/// rounded rectangle or a circle.
fn macro_class(name: &str, exact: Option<Exact>) -> String {
    match exact {
        Some(Exact::RoundRect { w, h, r, .. }) if r > 0.0 => {
            format!("{name} {}x{} r{}", num(w), num(h), num(r))
        }
        Some(Exact::RoundRect { w, h, .. }) => format!("{name} {}x{}", num(w), num(h)),
        Some(Exact::Circle { d }) => format!("{name} {}", num(d)),
        None => name.to_string(),
    }
}
