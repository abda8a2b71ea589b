//! Contact (`sim::contact`): resting contact, friction on a slope, energy of an elastic drop,
//! mesh colliders against analytic ones, parity of the host (source) and tensor (surrogate)
//! implementations, the stability guard, and bad collider files.

mod common;

use std::path::Path;

use burn::tensor::Device;
use springtime::data::Track;
use springtime::model::SpringNet;
use springtime::sim::contact::{Collider, ColliderConfig};
use springtime::sim::{Contact, ContactAt, ContactParams, Physics};
use springtime::source::{ClothSim, SpringCloth};

type V3 = [f64; 3];

const G: f64 = 9.81;

fn collider(toml_text: &str) -> Collider {
    let c: ColliderConfig = toml::from_str(toml_text).unwrap();
    c.build(Path::new("."), "test").unwrap()
}

fn params(damping: f64) -> ContactParams {
    ContactParams {
        thickness: 0.05,
        stiffness: 2.5e5,
        damping,
    }
}

/// A 5 × 5 spring sheet 2 m wide (m = 0.032 kg) with spring damping `b` and Rayleigh `c`.
fn sheet(b: f64, rayleigh: f64) -> SpringCloth {
    let mut cfg = common::source(5, &[50.0], 1.0);
    cfg.damping = b;
    cfg.rayleigh = rayleigh;
    SpringCloth::from_config(&cfg)
}

/// The flat rest sheet turned by `tilt` degrees about x, lifted by `lift` along its normal.
fn placed(cloth: &SpringCloth, tilt: f64, lift: f64) -> Vec<V3> {
    let (s, c) = tilt.to_radians().sin_cos();
    let n = [0.0, -s, c];
    cloth
        .topology
        .rest_positions()
        .iter()
        .map(|p| {
            let (x, y) = (p[0] - 1.0, p[1] - 1.0);
            [x + lift * n[0], y * c + lift * n[1], y * s + lift * n[2]]
        })
        .collect()
}

/// The test sheet dropped flat from `lift` onto `collider` alone: where it is after 800 steps.
fn dropped(collider: &Collider, lift: f64) -> Vec<V3> {
    let cloth = sheet(0.5, 0.1);
    let contact = Contact::new(vec![collider.clone()], params(250.0));
    let mut x = placed(&cloth, 0.0, lift);
    let mut v = vec![[0.0; 3]; x.len()];
    simulate(&cloth, &mut x, &mut v, &contact, 800);
    x
}

/// The largest coordinate difference between two configurations, m.
fn largest_difference(a: &[V3], b: &[V3]) -> f64 {
    a.iter()
        .zip(b)
        .flat_map(|(p, q)| (0..3).map(move |c| (p[c] - q[c]).abs()))
        .fold(0.0, f64::max)
}

fn simulate(cloth: &SpringCloth, x: &mut [V3], v: &mut [V3], contact: &Contact, steps: usize) {
    let pinned = vec![false; x.len()];
    let mut scratch = Vec::new();
    for step in 0..steps {
        let at = ContactAt {
            contact,
            time: step as f64 * 1e-3,
        };
        cloth.step(x, v, &pinned, 1e-3, Some(at), &mut scratch);
    }
}

fn centroid(x: &[V3]) -> V3 {
    [0, 1, 2].map(|c| x.iter().map(|p| p[c]).sum::<f64>() / x.len() as f64)
}

#[test]
fn a_sheet_on_the_ground_rests_at_the_contact_thickness_without_drift() {
    let cloth = sheet(0.5, 0.1);
    let contact = Contact::new(vec![collider("kind = \"plane\"")], params(250.0));
    let mut x = placed(&cloth, 0.0, 0.05);
    let x0 = x.clone();
    let mut v = vec![[0.0; 3]; x.len()];
    simulate(&cloth, &mut x, &mut v, &contact, 3000);
    let rest = 0.05 - G / 2.5e5;
    for (p, q) in x.iter().zip(&x0) {
        assert!(
            (p[2] - rest).abs() < 1e-8,
            "z = {} vs δ − g/κ = {rest}",
            p[2]
        );
        assert!((p[0] - q[0]).abs() < 1e-12 && (p[1] - q[1]).abs() < 1e-12);
    }
    assert!(v.iter().flatten().all(|c| c.abs() < 1e-7), "still moving");
    // Zero net force: gravity balanced by the contact layer, nothing sideways.
    let mut f = vec![[0.0; 3]; x.len()];
    cloth.net_forces(&x, &v, &mut f);
    contact.apply(
        3.0,
        1e-3,
        &x,
        &v,
        &vec![false; x.len()],
        |_| cloth.mass,
        &mut f,
    );
    let weight = cloth.mass * G;
    assert!(f.iter().flatten().all(|c| c.abs() < 1e-6 * weight), "{f:?}");
    // The layer was never crushed beyond the initial settling.
    assert!(contact.deepest() < 2.0 * G / 2.5e5, "{}", contact.deepest());
}

#[test]
fn friction_holds_a_sheet_below_the_friction_angle_and_lets_it_slide_above() {
    let tilt = 20.0f64;
    let slope = |mu: f64| {
        collider(&format!(
            "kind = \"plane\"\nrotation_deg = [{tilt}, 0.0, 0.0]\nfriction = {mu}"
        ))
    };
    // At rest on the slope (sunk by the weight's normal part).
    let lift = 0.05 - G * tilt.to_radians().cos() / 2.5e5;
    let down = [0.0, -tilt.to_radians().cos(), -tilt.to_radians().sin()];
    let travel = |mu: f64| {
        let cloth = sheet(0.5, 0.0);
        let contact = Contact::new(vec![slope(mu)], params(250.0));
        let mut x = placed(&cloth, tilt, lift);
        let start = centroid(&x);
        let mut v = vec![[0.0; 3]; x.len()];
        simulate(&cloth, &mut x, &mut v, &contact, 1000);
        let end = centroid(&x);
        (0..3).map(|c| (end[c] - start[c]) * down[c]).sum::<f64>()
    };
    // tan 20° = 0.364: μ = 0.5 holds, μ = 0.2 slides with a = g (sin θ − μ cos θ).
    let held = travel(0.5);
    assert!(held.abs() < 1e-6, "slid {held} m with μ = 0.5");
    let (s, c) = tilt.to_radians().sin_cos();
    let expected = 0.5 * G * (s - 0.2 * c) * 1.0f64.powi(2);
    let slid = travel(0.2);
    assert!(
        (slid - expected).abs() < 0.01 * expected,
        "slid {slid} m with μ = 0.2, expected {expected} m"
    );
}

/// Drops the sheet from 0.3 m onto the ground (frictionless, no cloth damping), stepping by
/// `h` for 0.6 s; the largest relative energy change once it is out of the contact layer
/// again, and the highest point after the bounce.
fn drop(h: f64, damping: f64) -> (f64, f64) {
    let cloth = sheet(0.0, 0.0);
    let p = ContactParams {
        thickness: 0.05,
        stiffness: 2.5e5,
        damping,
    };
    let contact = Contact::new(vec![collider("kind = \"plane\"\nfriction = 0.0")], p);
    let mut x = placed(&cloth, 0.0, 0.3);
    let mut v = vec![[0.0; 3]; x.len()];
    let m = cloth.mass;
    let energy = |x: &[V3], v: &[V3]| -> f64 {
        x.iter()
            .zip(v)
            .map(|(q, w)| {
                let phi = (0.05 - q[2]).max(0.0);
                0.5 * m * (w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
                    + m * G * q[2]
                    + 0.5 * m * p.stiffness * phi * phi
            })
            .sum()
    };
    let e0 = energy(&x, &v);
    let (mut change, mut peak) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    let mut touched = false;
    let pinned = vec![false; x.len()];
    let mut scratch = Vec::new();
    for step in 0..(0.6 / h).round() as usize {
        let at = ContactAt {
            contact: &contact,
            time: step as f64 * h,
        };
        cloth.step(&mut x, &mut v, &pinned, h, Some(at), &mut scratch);
        touched |= x[0][2] < 0.05;
        if touched && x[0][2] > 0.05 {
            peak = peak.max(x[0][2]);
            change = change.max(energy(&x, &v) / e0 - 1.0);
        }
    }
    assert!(touched, "the sheet never reached the ground");
    (change, peak)
}

#[test]
fn an_elastic_drop_without_friction_or_damping_gains_no_energy() {
    // Semi-implicit Euler enters and leaves the layer between steps: at h²κ = 0.25 (the
    // default) a bounce may change the energy by a little; the change vanishes with the step.
    let (coarse, peak) = drop(1e-3, 0.0);
    assert!(coarse < 0.025, "energy gain {coarse} at h = 1 ms");
    assert!(peak > 0.25 && peak < 0.31, "bounced to {peak} m from 0.3 m");
    let (fine, peak) = drop(1.25e-4, 0.0);
    assert!(fine < 1e-3, "energy gain {fine} at h = 0.125 ms");
    assert!((peak - 0.3).abs() < 2e-3, "bounced to {peak} m from 0.3 m");
    // Approach damping (the default ζ = 0.25/h) takes energy out of every impact.
    let (damped, peak) = drop(1e-3, 250.0);
    assert!(
        damped < -0.1,
        "energy change {damped} with approach damping"
    );
    assert!(peak < 0.25, "bounced to {peak} m");
}

/// A closed box mesh of half extents `h`, outward faces.
fn box_obj(h: V3) -> String {
    let mut s = String::new();
    for i in 0..8 {
        let p = [0, 1, 2].map(|c| if (i >> c) & 1 == 1 { h[c] } else { -h[c] });
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    // Faces as quads, counter-clockwise seen from outside (vertex ids 1-based: bit c = axis c).
    for f in [
        [1, 3, 4, 2], // -z
        [5, 6, 8, 7], // +z
        [1, 2, 6, 5], // -y
        [3, 7, 8, 4], // +y
        [1, 5, 7, 3], // -x
        [2, 4, 8, 6], // +x
    ] {
        s += &format!("f {} {} {} {}\n", f[0], f[1], f[2], f[3]);
    }
    s
}

/// A UV sphere of radius `r` with `nu × nv` cells.
fn sphere_obj(r: f64, nu: usize, nv: usize) -> String {
    use std::f64::consts::PI;
    let mut s = format!("v 0 0 {}\nv 0 0 {}\n", -r, r);
    for j in 1..nv {
        let b = -PI / 2.0 + PI * j as f64 / nv as f64;
        for i in 0..nu {
            let a = 2.0 * PI * i as f64 / nu as f64;
            s += &format!(
                "v {} {} {}\n",
                r * b.cos() * a.cos(),
                r * b.cos() * a.sin(),
                r * b.sin()
            );
        }
    }
    let ring = |j: usize, i: usize| 3 + (j - 1) * nu + i % nu;
    for i in 0..nu {
        s += &format!("f 1 {} {}\n", ring(1, i + 1), ring(1, i));
        s += &format!("f 2 {} {}\n", ring(nv - 1, i), ring(nv - 1, i + 1));
        for j in 1..nv - 1 {
            s += &format!(
                "f {} {} {} {}\n",
                ring(j, i),
                ring(j, i + 1),
                ring(j + 1, i + 1),
                ring(j + 1, i)
            );
        }
    }
    s
}

#[test]
fn mesh_colliders_match_the_analytic_box_and_sphere() {
    let dir = common::temp_dir("contact-mesh");
    std::fs::write(dir.join("box.obj"), box_obj([1.0, 0.5, 0.3])).unwrap();
    std::fs::write(dir.join("sphere.obj"), sphere_obj(1.0, 96, 48)).unwrap();
    let built = |text: &str| {
        let c: ColliderConfig = toml::from_str(text).unwrap();
        c.build(&dir, "test").unwrap()
    };
    let pose = "translation = [0.3, -0.2, 0.1]\nrotation_deg = [10.0, 20.0, 30.0]";
    let box_mesh = built(&format!("kind = \"mesh\"\nmesh = \"box.obj\"\n{pose}"));
    let box_shape = built(&format!(
        "kind = \"rounded_box\"\nhalf_extents = [1.0, 0.5, 0.3]\n{pose}"
    ));
    let sphere_mesh = built(&format!("kind = \"mesh\"\nmesh = \"sphere.obj\"\n{pose}"));
    let sphere = built(&format!("kind = \"sphere\"\nradius = 1.0\n{pose}"));
    let mut worst_box: f64 = 0.0;
    let mut worst_sphere: f64 = 0.0;
    for i in 0..2000 {
        let q = [0.37, 0.61, 0.83].map(|f: f64| 2.5 * ((i as f64 * f * 7.1).sin()));
        let (a, b) = (box_mesh.query(0.0, q), box_shape.query(0.0, q));
        worst_box = worst_box.max((a.distance - b.distance).abs());
        if a.distance.abs() > 1e-3 {
            let dot = (0..3).map(|c| a.normal[c] * b.normal[c]).sum::<f64>();
            assert!(
                dot > 1.0 - 1e-9,
                "{q:?}: normals {:?} {:?}",
                a.normal,
                b.normal
            );
        }
        let (a, b) = (sphere_mesh.query(0.0, q), sphere.query(0.0, q));
        worst_sphere = worst_sphere.max((a.distance - b.distance).abs());
    }
    assert!(worst_box < 1e-9, "box mesh vs box: {worst_box}");
    // A 96 × 48 polygon sphere lies within r (1 − cos(π/48)) ≈ 2.1e-3 of the ball.
    assert!(worst_sphere < 2.2e-3, "sphere mesh vs ball: {worst_sphere}");
    // The same drop on both boxes ends in the same place.
    let (a, b) = (dropped(&box_mesh, 0.8), dropped(&box_shape, 0.8));
    let gap = largest_difference(&a, &b);
    assert!(gap < 1e-6, "drops differ by {gap} m");
    assert!(a.iter().any(|p| p[2] < 0.7), "the sheet did not fall");
}

#[test]
fn the_surrogate_with_the_true_springs_matches_the_source_through_contact() {
    // A sphere under the sheet, friction on: the host (f64) and tensor (f32) paths agree.
    let cloth = sheet(0.5, 0.1);
    let contact = Contact::new(
        vec![collider(
            "kind = \"sphere\"\nradius = 0.6\ntranslation = [0.1, 0.0, -0.6]\nfriction = 0.4",
        )],
        params(250.0),
    );
    let x0 = placed(&cloth, 0.0, 0.2);
    let mut x = x0.clone();
    let mut v = vec![[0.0; 3]; x.len()];
    let frames = 600;
    simulate(&cloth, &mut x, &mut v, &contact.clone(), frames);

    let device = Device::flex();
    let topo = &cloth.topology;
    let model = SpringNet::new(topo, &cloth.k, &cloth.b, &device);
    let physics = Physics {
        frame_dt: 1e-3,
        substeps: 1,
        mass: cloth.mass,
        rayleigh: cloth.rayleigh,
        gravity: cloth.gravity,
        viscosity: 0.0,
        shear_compression: 1.0,
    };
    let track = Track::at_rest(&x0);
    let tensor_contact = contact.clone();
    let end = common::last_frame(
        &model,
        &physics,
        Some(&tensor_contact),
        &track,
        frames,
        &device,
    );
    let gap = end
        .chunks(3)
        .zip(&x)
        .flat_map(|(a, b)| (0..3).map(move |c| (a[c] as f64 - b[c]).abs()))
        .fold(0.0, f64::max);
    let moved = x
        .iter()
        .zip(&x0)
        .map(|(a, b)| (a[2] - b[2]).abs())
        .fold(0.0, f64::max);
    assert!(moved > 0.2, "the sheet barely moved: {moved}");
    assert!(tensor_contact.deepest() > 0.0, "no contact happened");
    assert!(
        gap < 1e-4,
        "surrogate and source differ by {gap} m after {frames} steps"
    );
}

#[test]
fn the_guard_counts_the_contact_and_refuses_an_unstable_step() {
    let cloth = sheet(0.5, 0.1);
    let st = cloth.stability(1e-3);
    let soft = st.clone().with_contact(&params(250.0));
    assert!((soft.number() - st.number() - 0.75).abs() < 1e-9);
    assert!(soft.check("scene", false).is_ok());
    let hard = st.with_contact(&ContactParams {
        thickness: 0.05,
        stiffness: 1e7,
        damping: 250.0,
    });
    let err = hard.check("scene table", false).unwrap_err().to_string();
    assert!(
        err.contains("largest stable dt") && err.contains("contact"),
        "{err}"
    );
}

#[test]
fn bad_collider_meshes_are_refused_naming_the_file() {
    let dir = common::temp_dir("contact-bad");
    let build = |file: &str| {
        let c: ColliderConfig =
            toml::from_str(&format!("kind = \"mesh\"\nmesh = \"{file}\"")).unwrap();
        format!("{:#}", c.build(&dir, "scene.colliders[0]").unwrap_err())
    };
    let err = build("missing.obj");
    assert!(
        err.contains("missing.obj") && err.contains("scene.colliders[0]"),
        "{err}"
    );
    std::fs::write(dir.join("table.stl"), "solid x\nendsolid x\n").unwrap();
    assert!(
        build("table.stl").contains("not an .obj"),
        "{}",
        build("table.stl")
    );
    std::fs::write(dir.join("empty.obj"), "# nothing\n").unwrap();
    assert!(build("empty.obj").contains("no triangles"));
    std::fs::write(dir.join("garbage.obj"), "v 1 2\nf 1 2 3\n").unwrap();
    assert!(build("garbage.obj").contains("garbage.obj"));
    // A box with its top face missing has a hole.
    let open: String = box_obj([1.0; 3])
        .lines()
        .filter(|l| *l != "f 5 6 8 7")
        .map(|l| l.to_string() + "\n")
        .collect();
    std::fs::write(dir.join("open.obj"), open).unwrap();
    let err = build("open.obj");
    assert!(
        err.contains("open.obj") && err.contains("not closed"),
        "{err}"
    );
    // A fin: a third triangle on an edge of the box.
    let fin = box_obj([1.0; 3]) + "v 0 0 5\nf 1 2 9\n";
    std::fs::write(dir.join("fin.obj"), fin).unwrap();
    let err = build("fin.obj");
    assert!(
        err.contains("fin.obj") && err.contains("non-manifold"),
        "{err}"
    );
    // One face turned the wrong way.
    let flipped = box_obj([1.0; 3]).replace("f 5 6 8 7", "f 7 8 6 5");
    std::fs::write(dir.join("flipped.obj"), flipped).unwrap();
    let err = build("flipped.obj");
    assert!(err.contains("consistently oriented"), "{err}");
    // Shape parameters are checked per kind.
    let c: ColliderConfig = toml::from_str("kind = \"sphere\"").unwrap();
    let err = c.build(&dir, "scene.colliders[1]").unwrap_err().to_string();
    assert!(
        err.contains("scene.colliders[1]") && err.contains("radius"),
        "{err}"
    );
}

#[test]
fn a_rounded_box_is_rounded_exactly() {
    // Against the closed-form distance of a box of half sizes h rounded by r, to rounding
    // error (parry's own round shapes are projected by GJK: 9.8e-6 m off at worst here).
    let (h, r) = ([0.4, 0.25, 0.1], 0.15);
    let shape = collider(&format!(
        "kind = \"rounded_box\"\nhalf_extents = {h:?}\nradius = {r}\ntranslation = [0.3, -0.2, 0.1]"
    ));
    let mut worst: f64 = 0.0;
    for i in 0..2000 {
        let q = [0.37, 0.61, 0.83].map(|f: f64| 0.9 * ((i as f64 * f * 7.1).sin()));
        let p = [q[0] - 0.3, q[1] + 0.2, q[2] - 0.1];
        let out: Vec<f64> = (0..3).map(|c| p[c].abs() - h[c]).collect();
        let outside = out.iter().map(|v| v.max(0.0).powi(2)).sum::<f64>().sqrt();
        let inside = out.iter().copied().fold(f64::MIN, f64::max).min(0.0);
        let exact = outside + inside - r;
        worst = worst.max((shape.query(0.0, q).distance - exact).abs());
    }
    assert!(worst < 1e-12, "rounded box off by {worst} m");
    // A box of no size rounded by r is a ball of radius r: a sheet dropped on either ends in the
    // same place (the contact's reach-culled queries included).
    let ball = collider("kind = \"sphere\"\nradius = 0.3\ntranslation = [0.05, 0.0, 0.0]");
    let point = collider(
        "kind = \"rounded_box\"\nhalf_extents = [0.0, 0.0, 0.0]\nradius = 0.3\n\
         translation = [0.05, 0.0, 0.0]",
    );
    let (a, b) = (dropped(&ball, 0.4), dropped(&point, 0.4));
    let gap = largest_difference(&a, &b);
    assert!(gap < 1e-9, "drops differ by {gap} m");
    // It fell onto the ball and stayed outside it.
    let from_centre = |p: &[f64; 3]| ((p[0] - 0.05).powi(2) + p[1].powi(2) + p[2].powi(2)).sqrt();
    assert!(a.iter().any(|p| p[2] < 0.3), "the sheet did not fall");
    assert!(
        a.iter().all(|p| from_centre(p) > 0.29),
        "the sheet entered the ball"
    );
}

#[test]
fn lift_out_puts_points_at_the_resting_distance_of_every_collider() {
    // A ground plane and a sphere sunk halfway into it: points inside either, or within
    // `rest` of it, end exactly `rest` from the nearer surface and outside both; points
    // already farther stay where they are.
    let contact = Contact::new(
        vec![
            collider("kind = \"plane\""),
            collider("kind = \"sphere\"\nradius = 0.5"),
        ],
        params(250.0),
    );
    let rest = 0.05 - G / 2.5e5;
    let start: Vec<V3> = vec![
        [2.0, 0.0, -0.3],  // below the ground
        [0.0, 0.0, 0.2],   // inside the sphere
        [0.0, 0.45, 0.05], // inside the sphere, near the ground
        [2.0, 1.0, 0.7],   // clear of both
        [0.0, 0.0, 0.53],  // in the sphere's layer
    ];
    let mut x = start.clone();
    contact.lift_out(0.0, &mut x, rest);
    for (p, p0) in x.iter().zip(&start) {
        let d = contact
            .colliders
            .iter()
            .map(|c| c.query(0.0, *p).distance)
            .fold(f64::INFINITY, f64::min);
        let d0 = contact
            .colliders
            .iter()
            .map(|c| c.query(0.0, *p0).distance)
            .fold(f64::INFINITY, f64::min);
        if d0 >= rest {
            assert_eq!(p, p0, "a point clear of the layer moved");
        } else {
            assert!(
                (d - rest).abs() < 1e-9,
                "{p0:?} -> {p:?}: {d} m from a surface"
            );
        }
    }
    assert!(
        (x[0][2] - rest).abs() < 1e-12,
        "below the ground: straight up, {:?}",
        x[0]
    );
    let r = (x[1][0].powi(2) + x[1][1].powi(2) + x[1][2].powi(2)).sqrt();
    assert!((r - 0.5 - rest).abs() < 1e-9 && x[1][2] > 0.0, "{:?}", x[1]);
}
