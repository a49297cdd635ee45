//! VTK XML unstructured grids (`.vtu`), which ParaView opens.

use nalgebra::Vector3;
use std::fmt::Write as _;
use std::path::Path;

/// One data array attached to points or cells.
#[derive(Clone, Debug)]
pub enum VtkData {
    Scalars(String, Vec<f64>),
    Vectors(String, Vec<Vector3<f64>>),
}

/// Cell types used here (VTK codes).
pub const VTK_TRIANGLE: u8 = 5;
pub const VTK_HEXAHEDRON: u8 = 12;

#[derive(Clone, Debug, Default)]
pub struct Vtu {
    pub points: Vec<Vector3<f64>>,
    /// Node indices of each cell and its VTK type.
    pub cells: Vec<(Vec<usize>, u8)>,
    pub point_data: Vec<VtkData>,
    pub cell_data: Vec<VtkData>,
}

fn write_data(s: &mut String, d: &VtkData) {
    match d {
        VtkData::Scalars(name, v) => {
            let _ = writeln!(s, "<DataArray type=\"Float64\" Name=\"{name}\" format=\"ascii\">");
            for x in v {
                let _ = write!(s, "{x} ");
            }
        }
        VtkData::Vectors(name, v) => {
            let _ =
                writeln!(s, "<DataArray type=\"Float64\" Name=\"{name}\" NumberOfComponents=\"3\" format=\"ascii\">");
            for x in v {
                let _ = write!(s, "{} {} {} ", x.x, x.y, x.z);
            }
        }
    }
    s.push_str("\n</DataArray>\n");
}

impl Vtu {
    pub fn to_xml(&self) -> String {
        let mut s = String::new();
        s.push_str("<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\">\n<UnstructuredGrid>\n");
        let _ = writeln!(s, "<Piece NumberOfPoints=\"{}\" NumberOfCells=\"{}\">", self.points.len(), self.cells.len());
        s.push_str("<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n");
        for p in &self.points {
            let _ = write!(s, "{} {} {} ", p.x, p.y, p.z);
        }
        s.push_str(
            "\n</DataArray>\n</Points>\n<Cells>\n<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">\n",
        );
        for (c, _) in &self.cells {
            for i in c {
                let _ = write!(s, "{i} ");
            }
        }
        s.push_str("\n</DataArray>\n<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n");
        let mut off = 0;
        for (c, _) in &self.cells {
            off += c.len();
            let _ = write!(s, "{off} ");
        }
        s.push_str("\n</DataArray>\n<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n");
        for (_, t) in &self.cells {
            let _ = write!(s, "{t} ");
        }
        s.push_str("\n</DataArray>\n</Cells>\n");
        if !self.point_data.is_empty() {
            s.push_str("<PointData>\n");
            for d in &self.point_data {
                write_data(&mut s, d);
            }
            s.push_str("</PointData>\n");
        }
        if !self.cell_data.is_empty() {
            s.push_str("<CellData>\n");
            for d in &self.cell_data {
                write_data(&mut s, d);
            }
            s.push_str("</CellData>\n");
        }
        s.push_str("</Piece>\n</UnstructuredGrid>\n</VTKFile>\n");
        s
    }

    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        crate::write_atomic(path, self.to_xml().as_bytes())
    }
}
