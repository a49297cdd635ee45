//! Readers and writers: NIfTI (versions, byte orders, datatypes, affines, errors), NPZ,
//! meshes; fuzzed so that corrupt input gives an error, never a panic.

use nalgebra::{Matrix4, Point3, Vector3};
use proptest::prelude::*;
use std::path::{Path, PathBuf};
use umesh_core::mesh_io::{MeshIoError, read_closed_mesh, read_mesh, write_mesh};
use umesh_core::nifti_io::{self, NiftiError, ReadOptions, WriteType, read_volume, read_volume_bytes};
use umesh_core::npz::{Array, ArrayData, Npz, encode_npz};
use umesh_core::volume::Volume;

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("umesh-io-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Hand-built NIfTI header + data, any version and byte order, for cases the writer
/// does not produce.
struct Spec {
    version: u8,
    le: bool,
    dim: Vec<i64>,
    datatype: i16,
    bitpix: i16,
    pixdim: [f64; 4],
    slope: f64,
    inter: f64,
    qform_code: i32,
    sform_code: i32,
    quatern: [f64; 6],
    srow: [[f64; 4]; 3],
    data: Vec<u8>,
}

impl Spec {
    fn new(dims: [i64; 3], datatype: i16, bitpix: i16, data: Vec<u8>) -> Self {
        Spec {
            version: 1,
            le: true,
            dim: dims.to_vec(),
            datatype,
            bitpix,
            pixdim: [1.0, 2.0, 3.0, 4.0],
            slope: 0.0,
            inter: 0.0,
            qform_code: 0,
            sform_code: 1,
            quatern: [0.0; 6],
            srow: [[2.0, 0.0, 0.0, -10.0], [0.0, 3.0, 0.0, 20.0], [0.0, 0.0, 4.0, 5.0]],
            data,
        }
    }
    fn bytes(&self) -> Vec<u8> {
        let n = if self.version == 1 { 348 } else { 540 };
        let mut h = vec![0u8; n + 4];
        let le = self.le;
        let put = |h: &mut Vec<u8>, o: usize, b: &[u8]| {
            let mut b = b.to_vec();
            if !le {
                b.reverse();
            }
            h[o..o + b.len()].copy_from_slice(&b);
        };
        put(&mut h, 0, &(n as i32).to_le_bytes());
        let mut dim = vec![self.dim.len() as i64];
        dim.extend(&self.dim);
        dim.resize(8, 1);
        if self.version == 1 {
            for (i, d) in dim.iter().enumerate() {
                put(&mut h, 40 + 2 * i, &(*d as i16).to_le_bytes());
            }
            put(&mut h, 70, &self.datatype.to_le_bytes());
            put(&mut h, 72, &self.bitpix.to_le_bytes());
            for (i, p) in self.pixdim.iter().enumerate() {
                put(&mut h, 76 + 4 * i, &(*p as f32).to_le_bytes());
            }
            put(&mut h, 108, &(n as f32 + 4.0).to_le_bytes());
            put(&mut h, 112, &(self.slope as f32).to_le_bytes());
            put(&mut h, 116, &(self.inter as f32).to_le_bytes());
            h[123] = 2;
            put(&mut h, 252, &(self.qform_code as i16).to_le_bytes());
            put(&mut h, 254, &(self.sform_code as i16).to_le_bytes());
            for (i, q) in self.quatern.iter().enumerate() {
                put(&mut h, 256 + 4 * i, &(*q as f32).to_le_bytes());
            }
            for r in 0..3 {
                for c in 0..4 {
                    put(&mut h, 280 + 16 * r + 4 * c, &(self.srow[r][c] as f32).to_le_bytes());
                }
            }
            h[344..348].copy_from_slice(b"n+1\0");
        } else {
            h[4..12].copy_from_slice(b"n+2\0\r\n\x1a\n");
            put(&mut h, 12, &self.datatype.to_le_bytes());
            put(&mut h, 14, &self.bitpix.to_le_bytes());
            for (i, d) in dim.iter().enumerate() {
                put(&mut h, 16 + 8 * i, &d.to_le_bytes());
            }
            for (i, p) in self.pixdim.iter().enumerate() {
                put(&mut h, 104 + 8 * i, &p.to_le_bytes());
            }
            put(&mut h, 168, &(n as i64 + 4).to_le_bytes());
            put(&mut h, 176, &self.slope.to_le_bytes());
            put(&mut h, 184, &self.inter.to_le_bytes());
            put(&mut h, 344, &self.qform_code.to_le_bytes());
            put(&mut h, 348, &self.sform_code.to_le_bytes());
            for (i, q) in self.quatern.iter().enumerate() {
                put(&mut h, 352 + 8 * i, &q.to_le_bytes());
            }
            for r in 0..3 {
                for c in 0..4 {
                    put(&mut h, 400 + 32 * r + 8 * c, &self.srow[r][c].to_le_bytes());
                }
            }
            put(&mut h, 500, &2i32.to_le_bytes());
        }
        h.extend_from_slice(&self.data);
        h
    }
}

fn read(bytes: &[u8]) -> Result<Volume, NiftiError> {
    read_volume_bytes(Path::new("test.nii"), bytes, &ReadOptions::default())
}

fn encode<T: Copy>(vals: &[T], le: bool, f: impl Fn(T) -> Vec<u8>) -> Vec<u8> {
    vals.iter()
        .flat_map(|&v| {
            let mut b = f(v);
            if !le {
                b.reverse();
            }
            b
        })
        .collect()
}

#[test]
fn every_datatype_both_byte_orders_and_both_versions_decode_with_scaling() {
    let vals: Vec<f64> = (0..24).map(|i| i as f64 - 3.0).collect();
    for version in [1u8, 2] {
        for le in [true, false] {
            let cases: Vec<(i16, i16, Vec<u8>, bool)> = vec![
                (2, 8, vals.iter().map(|&v| (v + 3.0) as u8).collect(), false),
                (256, 8, vals.iter().map(|&v| v as i8 as u8).collect(), true),
                (4, 16, encode(&vals, le, |v| (v as i16).to_le_bytes().to_vec()), true),
                (512, 16, encode(&vals, le, |v| ((v + 3.0) as u16).to_le_bytes().to_vec()), false),
                (8, 32, encode(&vals, le, |v| (v as i32).to_le_bytes().to_vec()), true),
                (768, 32, encode(&vals, le, |v| ((v + 3.0) as u32).to_le_bytes().to_vec()), false),
                (1024, 64, encode(&vals, le, |v| (v as i64).to_le_bytes().to_vec()), true),
                (1280, 64, encode(&vals, le, |v| ((v + 3.0) as u64).to_le_bytes().to_vec()), false),
                (16, 32, encode(&vals, le, |v| (v as f32).to_le_bytes().to_vec()), true),
                (64, 64, encode(&vals, le, |v| v.to_le_bytes().to_vec()), true),
            ];
            for (dt, bp, data, signed) in cases {
                let mut s = Spec::new([2, 3, 4], dt, bp, data);
                s.version = version;
                s.le = le;
                s.slope = 2.0;
                s.inter = 1.0;
                let v = read(&s.bytes()).unwrap_or_else(|e| panic!("v{version} le={le} dt={dt}: {e}"));
                assert_eq!(v.dims, [2, 3, 4]);
                for (i, &x) in v.data.iter().enumerate() {
                    let raw = if signed { vals[i] } else { vals[i] + 3.0 };
                    assert_eq!(x as f64, raw * 2.0 + 1.0, "v{version} le={le} dt={dt} voxel {i}");
                }
            }
        }
    }
}

fn map(v: &Volume, ijk: [f64; 3]) -> Vector3<f64> {
    v.world_from_voxel.transform_point(&Point3::new(ijk[0], ijk[1], ijk[2])).coords
}

#[test]
fn affines_follow_the_standard_sform_then_qform_then_fallback() {
    let data = vec![0u8; 24];
    // sform (code > 0) wins over qform.
    let mut s = Spec::new([2, 3, 4], 2, 8, data.clone());
    s.qform_code = 1;
    s.quatern = [0.0, 0.0, 1.0, 7.0, 8.0, 9.0];
    let v = read(&s.bytes()).unwrap();
    assert!((map(&v, [1.0, 1.0, 1.0]) - Vector3::new(-8.0, 23.0, 9.0)).norm() < 1e-6);
    // qform only: quaternion (b, c, d) = (0, 0, 1) is a 180 degree turn about z.
    s.sform_code = 0;
    let v = read(&s.bytes()).unwrap();
    // pixdim 2, 3, 4; R = diag(-1, -1, 1); offset (7, 8, 9).
    assert!(
        (map(&v, [1.0, 1.0, 1.0]) - Vector3::new(7.0 - 2.0, 8.0 - 3.0, 9.0 + 4.0)).norm() < 1e-5,
        "{:?}",
        map(&v, [1.0, 1.0, 1.0])
    );
    // qfac = -1 flips the third axis.
    s.pixdim[0] = -1.0;
    let v = read(&s.bytes()).unwrap();
    assert!((map(&v, [0.0, 0.0, 1.0]) - Vector3::new(7.0, 8.0, 9.0 - 4.0)).norm() < 1e-5);
    // Neither: pixdim scaling.
    s.qform_code = 0;
    s.pixdim[0] = 1.0;
    let v = read(&s.bytes()).unwrap();
    assert!((map(&v, [1.0, 2.0, 3.0]) - Vector3::new(2.0, 6.0, 12.0)).norm() < 1e-9);
    // LPS-stored data (negative x and y axes in the sform) maps into RAS as written.
    let mut s = Spec::new([2, 3, 4], 2, 8, data);
    s.srow = [[-1.5, 0.0, 0.0, 100.0], [0.0, -1.5, 0.0, 50.0], [0.0, 0.0, 2.5, -30.0]];
    let v = read(&s.bytes()).unwrap();
    assert!((map(&v, [1.0, 2.0, 3.0]) - Vector3::new(98.5, 47.0, -22.5)).norm() < 1e-6);
    assert!((v.voxel_volume_mm3() - 1.5 * 1.5 * 2.5).abs() < 1e-9);
}

#[test]
fn writer_round_trips_and_agrees_with_the_nifti_crate() {
    let mut m = Matrix4::identity();
    // A rotated, anisotropic affine with a reflection (as LPS data converted to RAS has).
    let r = nalgebra::Rotation3::from_euler_angles(0.1, -0.2, 0.3).into_inner()
        * nalgebra::Matrix3::from_diagonal(&Vector3::new(-0.8, 0.9, 2.5));
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m[(0, 3)] = 12.0;
    m[(1, 3)] = -7.0;
    m[(2, 3)] = 3.5;
    let mut vol = Volume::new([5, 4, 3], m);
    for (i, v) in vol.data.iter_mut().enumerate() {
        *v = (i % 7) as f32;
    }
    vol.label_names.insert(3, "liver".into());
    for (name, ty) in [("rt.nii", WriteType::U8), ("rt.nii.gz", WriteType::I16), ("rt32.nii.gz", WriteType::F32)] {
        let p = tmp(name);
        nifti_io::write_volume(&p, &vol, ty).unwrap();
        let back = read_volume(&p, &ReadOptions::default()).unwrap();
        assert_eq!(back.dims, vol.dims);
        assert_eq!(back.data, vol.data);
        assert!((back.world_from_voxel - m).amax() < 1e-4, "{name}");
        assert_eq!(back.label_names.get(&3).map(String::as_str), Some("liver"));
        // The nifti crate reads the same header and the same voxels.
        use nifti::{NiftiObject, RandomAccessNiftiVolume, ReaderOptions};
        let obj = ReaderOptions::new().read_file(&p).unwrap();
        let hdr = obj.header();
        assert_eq!(&hdr.dim[1..4], &[5, 4, 3]);
        assert_eq!(hdr.sform_code, 1);
        for r in 0..3 {
            for c in 0..4 {
                let srow = [hdr.srow_x, hdr.srow_y, hdr.srow_z][r];
                assert!((srow[c] as f64 - m[(r, c)]).abs() < 1e-4);
            }
        }
        let volume = obj.volume();
        assert_eq!(volume.get_f64(&[2, 3, 1]).unwrap() as f32, vol.data[vol.index(2, 3, 1)]);
    }
    // Header + image pair.
    let hdr = tmp("pair.hdr");
    let img = tmp("pair.img");
    let mut s = Spec::new([2, 3, 4], 2, 8, vec![]);
    let mut b = s.bytes();
    b[344..348].copy_from_slice(b"ni1\0");
    b[108..112].copy_from_slice(&0f32.to_le_bytes());
    std::fs::write(&hdr, &b[..352]).unwrap();
    std::fs::write(&img, (0..24u8).collect::<Vec<_>>()).unwrap();
    let v = read_volume(&hdr, &ReadOptions::default()).unwrap();
    assert_eq!(v.data[23], 23.0);
    let v2 = read_volume(&img, &ReadOptions::default()).unwrap();
    assert_eq!(v2.data, v.data);
    s.version = 2;
    let _ = s;
}

#[test]
fn bad_nifti_input_gives_one_clear_error_naming_the_file() {
    let good = Spec::new([2, 3, 4], 2, 8, vec![1; 24]).bytes();
    let check = |bytes: &[u8], want: &str| {
        let p = tmp("bad.nii");
        std::fs::write(&p, bytes).unwrap();
        let e = read_volume(&p, &ReadOptions { max_voxels: 1_000_000 }).unwrap_err().to_string();
        assert!(e.contains("bad.nii"), "error lacks the file name: {e}");
        assert!(e.to_lowercase().contains(want), "expected {want:?} in {e:?}");
    };
    check(&good[..good.len() - 5], "truncated");
    check(&good[..200], "header");
    check(b"", "header");
    check(b"hello world, this is not a nifti file at all", "not a nifti");
    let mut s = Spec::new([2, 3, 4], 1536, 128, vec![0; 24 * 16]);
    check(&s.bytes(), "unsupported");
    s = Spec::new([2, 3, 4], 999, 8, vec![0; 24]);
    check(&s.bytes(), "unsupported");
    s = Spec::new([2, 3, 4], 2, 8, vec![0; 72]);
    s.dim = vec![2, 3, 4, 3];
    check(&s.bytes(), "4-d");
    s.dim = vec![2, 3];
    check(&s.bytes(), "2-d");
    s = Spec::new([30000, 30000, 30000], 2, 8, vec![0; 16]);
    s.version = 2;
    check(&s.bytes(), "limit");
    s = Spec::new([2, 3, 4], 2, 8, vec![0; 24]);
    s.srow = [[0.0; 4]; 3];
    check(&s.bytes(), "singular");
    // Without an sform the voxel sizes come from pixdim: zero, negative or NaN is an error,
    // not a silent 1 mm.
    for bad_size in [0.0, -2.0, f64::NAN] {
        s = Spec::new([2, 3, 4], 2, 8, vec![0; 24]);
        s.sform_code = 0;
        s.pixdim[2] = bad_size;
        check(&s.bytes(), "pixdim");
        s.qform_code = 1;
        check(&s.bytes(), "pixdim");
    }
    // A NaN or infinite vox_offset is named as such, not read as 0.
    for bad_offset in [f32::NAN, f32::INFINITY] {
        let mut bytes = Spec::new([2, 3, 4], 2, 8, vec![0; 24]).bytes();
        bytes[108..112].copy_from_slice(&bad_offset.to_le_bytes());
        check(&bytes, &format!("vox_offset {bad_offset}").to_lowercase());
    }
    let missing = read_volume(Path::new("/nonexistent/seg.nii.gz"), &ReadOptions::default()).unwrap_err().to_string();
    assert!(missing.contains("/nonexistent/seg.nii.gz"));
    // A truncated gzip stream.
    let p = tmp("full.nii.gz");
    let mut vol = Volume::new([10, 10, 10], Matrix4::identity());
    vol.data.iter_mut().enumerate().for_each(|(i, v)| *v = (i % 5) as f32);
    nifti_io::write_volume(&p, &vol, WriteType::F32).unwrap();
    let gz = std::fs::read(&p).unwrap();
    let e = read(&gz[..gz.len() / 2]).unwrap_err().to_string();
    assert!(e.contains("test.nii"), "{e}");
}

#[test]
fn npz_round_trips_all_types_and_rejects_corruption() {
    let arrays = vec![
        ("a", Array::f32(vec![2, 3], vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5])),
        ("b", Array::f64(vec![3], vec![1e-300, -2.0, f64::MAX])),
        ("c", Array::i64(vec![2, 2], vec![-1, 2, 3, i64::MAX])),
        ("d", Array::new(vec![4], ArrayData::U8(vec![1, 2, 3, 255]))),
        ("e", Array::scalar_f64(3.25)),
        ("f", Array::new(vec![0, 3], ArrayData::F32(vec![]))),
    ];
    let bytes = encode_npz(&arrays).unwrap();
    // Deterministic bytes.
    assert_eq!(bytes, encode_npz(&arrays).unwrap());
    let npz = Npz::from_bytes(Path::new("x.npz"), &bytes).unwrap();
    for (name, a) in &arrays {
        assert_eq!(npz.get(name).unwrap(), a);
    }
    assert!(npz.get("zzz").unwrap_err().to_string().contains("'zzz' is missing"));
    assert!(Npz::from_bytes(Path::new("x.npz"), &bytes[..bytes.len() / 2]).is_err());
    // Fortran order and big-endian arrays written by numpy read correctly.
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    let header = "{'descr': '>i4', 'fortran_order': True, 'shape': (2, 3), }";
    let mut h = header.to_string();
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    npy.extend_from_slice(&(h.len() as u16).to_le_bytes());
    npy.extend_from_slice(h.as_bytes());
    for v in [1i32, 4, 2, 5, 3, 6] {
        npy.extend_from_slice(&v.to_be_bytes());
    }
    let a = Array::from_npy(&npy).unwrap();
    assert_eq!(a.shape, vec![2, 3]);
    assert_eq!(a.data, ArrayData::I32(vec![1, 2, 3, 4, 5, 6]));
}

fn cube() -> umesh_core::mesh::TriMesh {
    let positions: Vec<Vector3<f64>> =
        (0..8).map(|i| Vector3::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64) * 10.0).collect();
    let triangles = vec![
        [0, 2, 1],
        [1, 2, 3],
        [4, 5, 6],
        [5, 7, 6],
        [0, 1, 4],
        [1, 5, 4],
        [2, 6, 3],
        [3, 6, 7],
        [0, 4, 2],
        [2, 4, 6],
        [1, 3, 5],
        [3, 7, 5],
    ];
    umesh_core::mesh::TriMesh { positions, triangles }
}

#[test]
fn meshes_round_trip_in_every_format_and_open_meshes_are_refused() {
    let m = cube();
    assert!(m.topology().is_watertight());
    // A surface with no triangle (a one-voxel organ sampled away) encloses nothing.
    assert!(!umesh_core::mesh::TriMesh { positions: vec![], triangles: vec![] }.topology().is_watertight());
    assert!((m.signed_volume_mm3() - 1000.0).abs() < 1e-9);
    for ext in ["obj", "ply", "stl"] {
        let p = tmp(&format!("cube.{ext}"));
        write_mesh(&p, &m).unwrap();
        let back = read_closed_mesh(&p).unwrap();
        assert_eq!(back.triangles.len(), 12, "{ext}");
        assert!((back.signed_volume_mm3() - 1000.0).abs() < 1e-3, "{ext}");
    }
    // ASCII PLY and ASCII STL.
    let p = tmp("tri.ply");
    std::fs::write(&p, "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").unwrap();
    assert_eq!(read_mesh(&p).unwrap().triangles, vec![[0, 1, 2]]);
    let p = tmp("tri.stl");
    std::fs::write(
        &p,
        "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n",
    )
    .unwrap();
    assert_eq!(read_mesh(&p).unwrap().triangles.len(), 1);
    // An open mesh (a cube without its lid) is refused with the reason.
    let mut open = cube();
    open.triangles.truncate(10);
    let p = tmp("open.obj");
    write_mesh(&p, &open).unwrap();
    match read_closed_mesh(&p) {
        Err(e @ MeshIoError::Open { .. }) => {
            assert!(e.to_string().contains("open.obj") && e.to_string().contains("not closed"))
        }
        other => panic!("{other:?}"),
    }
    // Inside-out meshes are flipped; voxelising gives the right volume.
    let mut inv = cube();
    inv.triangles.iter_mut().for_each(|t| t.swap(1, 2));
    let p = tmp("inv.obj");
    write_mesh(&p, &inv).unwrap();
    let fixed = read_closed_mesh(&p).unwrap();
    assert!(fixed.signed_volume_mm3() > 0.0);
    let mask = fixed.voxelize(0.5).unwrap();
    assert!((mask.volume_mm3() - 1000.0).abs() / 1000.0 < 0.1, "{}", mask.volume_mm3());
    // Unknown extension, bad indices.
    assert!(matches!(read_mesh(&tmp("x.abc")), Err(MeshIoError::UnknownFormat { .. }) | Err(MeshIoError::Io { .. })));
    let p = tmp("bad.obj");
    std::fs::write(&p, "v 0 0 0\nf 1 2 3\n").unwrap();
    assert!(read_mesh(&p).unwrap_err().to_string().contains("bad.obj"));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, failure_persistence: Some(Box::new(proptest::test_runner::FileFailurePersistence::WithSource("regressions"))), ..ProptestConfig::default() })]

    #[test]
    fn fuzzed_nifti_bytes_never_panic(flips in proptest::collection::vec((0usize..400, any::<u8>()), 0..12), cut in 0usize..420) {
        let mut b = Spec::new([2, 3, 4], 4, 16, vec![7; 48]).bytes();
        for (i, v) in flips {
            let n = b.len();
            b[i % n] = v;
        }
        b.truncate(cut.max(1));
        let _ = read(&b);
    }

    #[test]
    fn fuzzed_npz_and_mesh_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..600), flips in proptest::collection::vec((0usize..2000, any::<u8>()), 0..8)) {
        let _ = Npz::from_bytes(Path::new("f.npz"), &data);
        let mut good = encode_npz(&[("a", Array::f32(vec![3], vec![1.0, 2.0, 3.0]))]).unwrap();
        for (i, v) in &flips {
            let n = good.len();
            good[i % n] = *v;
        }
        let _ = Npz::from_bytes(Path::new("f.npz"), &good);
        let _ = Array::from_npy(&data);
        for ext in ["obj", "ply", "stl"] {
            let p = tmp(&format!("fuzz.{ext}"));
            std::fs::write(&p, &data).unwrap();
            let _ = read_mesh(&p);
        }
    }
}

#[test]
fn a_mask_folder_with_two_files_of_one_structure_and_an_organ_made_of_structures_are_refused() {
    use umesh_core::segmentation::{Segmentation, mask_folder};
    let d = tmp("twin-masks");
    std::fs::create_dir_all(&d).unwrap();
    let mut vol = Volume::new([4, 4, 4], Matrix4::identity());
    vol.data[21] = 1.0;
    nifti_io::write_volume(&d.join("liver.nii.gz"), &vol, WriteType::U8).unwrap();
    assert!(mask_folder(&d).is_ok());
    nifti_io::write_volume(&d.join("liver.nii"), &vol, WriteType::U8).unwrap();
    let e = mask_folder(&d).unwrap_err().to_string();
    assert!(e.contains("liver.nii") && e.contains("liver.nii.gz") && e.contains("same structure"), "{e}");
    let seg = Segmentation { source: "seg.nii".into(), volume: vol, organ_labels: vec![1], structure_labels: vec![1] };
    let e = seg.validate().unwrap_err().to_string();
    assert!(e.contains("seg.nii") && e.contains("structure cannot be the whole organ"), "{e}");
}

#[test]
fn a_segmentation_voxelised_from_a_mesh_reads_back_from_nifti_on_the_same_lattice_and_grid() {
    // Bounds and spacing not exact in single precision: NIfTI keeps f32, so before the lattice
    // was snapped the grid read back moved by about 1e-5 mm and its hash changed.
    let mut m = cube();
    for v in &mut m.positions {
        *v = *v * 3.3 + Vector3::new(0.123_456_789, 10.333_333_3, -7.777_777_7);
    }
    let p = tmp("odd_cube.obj");
    write_mesh(&p, &m).unwrap();
    let seg = umesh_core::segmentation::load_meshes(&p, &[], 0.7, 1.0).unwrap();
    let nii = tmp("odd_cube.nii.gz");
    nifti_io::write_volume(&nii, &seg.volume, WriteType::U8).unwrap();
    let back = read_volume(&nii, &ReadOptions::default()).unwrap();
    assert_eq!(back.dims, seg.volume.dims);
    assert_eq!(back.world_from_voxel, seg.volume.world_from_voxel, "the lattice moved in the round trip");
    let settings = umesh_core::grid::GridSettings { cell_size_mm: 3.0, ..Default::default() };
    let grid = |v: &Volume| {
        let mask = v.mask(&[1]);
        umesh_core::grid::ImmersedGrid::from_mask(
            &mask,
            &settings,
            &umesh_core::Progress::none(),
            &umesh_core::Cancel::new(),
        )
        .unwrap()
    };
    assert_eq!(grid(&back).to_npz_arrays(), grid(&seg.volume).to_npz_arrays());
}
