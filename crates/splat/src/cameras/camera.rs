//! The one camera model used inside vcedit: a pinhole OpenCV camera.
//!
//! Every loader (COLMAP, transforms.json, INRIA cameras.json, orbits) converts into this. x right, y down,
//! z forward; pixel (i, j) is centred at (i + 0.5, j + 0.5), so a principal point of (w/2, h/2) is the
//! image centre.

/// A pinhole camera with OpenCV axes.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// A name for outputs (e.g. the image file stem).
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Focal lengths in pixels.
    pub fx: f64,
    pub fy: f64,
    /// Principal point in pixels (pixel-centre convention above).
    pub cx: f64,
    pub cy: f64,
    /// World-to-camera rotation, row-major.
    pub rotation: [[f64; 3]; 3],
    /// World-to-camera translation.
    pub translation: [f64; 3],
}

impl Camera {
    /// Camera centre in world coordinates: -R^T t.
    pub fn center(&self) -> [f64; 3] {
        let r = &self.rotation;
        let t = &self.translation;
        let mut c = [0.0; 3];
        for (a, ca) in c.iter_mut().enumerate() {
            *ca = -(r[0][a] * t[0] + r[1][a] * t[1] + r[2][a] * t[2]);
        }
        c
    }

    /// Maps a world point into camera coordinates.
    pub fn world_to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        let t = &self.translation;
        let mut q = [0.0; 3];
        for (a, qa) in q.iter_mut().enumerate() {
            *qa = r[a][0] * p[0] + r[a][1] * p[1] + r[a][2] * p[2] + t[a];
        }
        q
    }

    /// Horizontal and vertical field of view in radians.
    pub fn fov(&self) -> (f64, f64) {
        (
            2.0 * (self.width as f64 / (2.0 * self.fx)).atan(),
            2.0 * (self.height as f64 / (2.0 * self.fy)).atan(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn center_roundtrip() {
        let cam = Camera {
            name: "c".into(),
            width: 4,
            height: 4,
            fx: 2.0,
            fy: 2.0,
            cx: 2.0,
            cy: 2.0,
            rotation: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [1.0, 2.0, 3.0],
        };
        let c = cam.center();
        let q = cam.world_to_camera(c);
        for v in q {
            assert!(v.abs() < 1e-12);
        }
    }
}
