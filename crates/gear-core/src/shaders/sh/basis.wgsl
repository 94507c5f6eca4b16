// The real spherical-harmonic basis of degree <= DEGREE on a unit direction, and its gradient
// (as in the host's sh/basis.rs). Specialised with DEGREE, K = (DEGREE + 1)^2 and
// MIN_DIR_NORM (directions shorter than it are the zero vector, with no gradient). Basis
// arrays always hold 16 entries, of which the first K are used: a constant index past a
// shorter array would not compile, even in a branch the degree removes.

const C0: f32 = 0.28209479177387814;
const C1: f32 = 0.4886025119029199;
const C2_0: f32 = 1.0925484305920792;
const C2_1: f32 = -1.0925484305920792;
const C2_2: f32 = 0.31539156525252005;
const C2_3: f32 = -1.0925484305920792;
const C2_4: f32 = 0.5462742152960396;
const C3_0: f32 = -0.5900435899266435;
const C3_1: f32 = 2.890611442640554;
const C3_2: f32 = -0.4570457994644658;
const C3_3: f32 = 0.3731763325901154;
const C3_4: f32 = -0.4570457994644658;
const C3_5: f32 = 1.445305721320277;
const C3_6: f32 = -0.5900435899266435;

// A direction's unit vector and length; length 0 (and the zero vector) when it is shorter
// than MIN_DIR_NORM. Scaled by the largest component so the squared norm cannot over- or
// underflow.
struct Unit {
    u: vec3<f32>,
    norm: f32,
}

fn unit_of(d: vec3<f32>) -> Unit {
    let m = max(abs(d.x), max(abs(d.y), abs(d.z)));
    if !(m > 0.0) {
        return Unit(vec3<f32>(0.0), 0.0);
    }
    let s = d / m;
    let len = sqrt(dot(s, s));
    let norm = m * len;
    if norm < MIN_DIR_NORM {
        return Unit(vec3<f32>(0.0), 0.0);
    }
    return Unit(s / len, norm);
}

fn basis(u: vec3<f32>) -> array<f32, 16> {
    var y: array<f32, 16>;
    y[0] = C0;
    if DEGREE >= 1u {
        y[1] = -C1 * u.y;
        y[2] = C1 * u.z;
        y[3] = -C1 * u.x;
    }
    if DEGREE >= 2u {
        let xx = u.x * u.x;
        let yy = u.y * u.y;
        let zz = u.z * u.z;
        y[4] = C2_0 * u.x * u.y;
        y[5] = C2_1 * u.y * u.z;
        y[6] = C2_2 * (2.0 * zz - xx - yy);
        y[7] = C2_3 * u.x * u.z;
        y[8] = C2_4 * (xx - yy);
        if DEGREE >= 3u {
            y[9] = C3_0 * u.y * (3.0 * xx - yy);
            y[10] = C3_1 * u.x * u.y * u.z;
            y[11] = C3_2 * u.y * (4.0 * zz - xx - yy);
            y[12] = C3_3 * u.z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            y[13] = C3_4 * u.x * (4.0 * zz - xx - yy);
            y[14] = C3_5 * u.z * (xx - yy);
            y[15] = C3_6 * u.x * (xx - 3.0 * yy);
        }
    }
    return y;
}

fn basis_gradient(u: vec3<f32>) -> array<vec3<f32>, 16> {
    var g: array<vec3<f32>, 16>;
    g[0] = vec3<f32>(0.0);
    let x = u.x;
    let y = u.y;
    let z = u.z;
    if DEGREE >= 1u {
        g[1] = vec3<f32>(0.0, -C1, 0.0);
        g[2] = vec3<f32>(0.0, 0.0, C1);
        g[3] = vec3<f32>(-C1, 0.0, 0.0);
    }
    if DEGREE >= 2u {
        g[4] = C2_0 * vec3<f32>(y, x, 0.0);
        g[5] = C2_1 * vec3<f32>(0.0, z, y);
        g[6] = C2_2 * vec3<f32>(-2.0 * x, -2.0 * y, 4.0 * z);
        g[7] = C2_3 * vec3<f32>(z, 0.0, x);
        g[8] = C2_4 * vec3<f32>(2.0 * x, -2.0 * y, 0.0);
        if DEGREE >= 3u {
            let xx = x * x;
            let yy = y * y;
            let zz = z * z;
            g[9] = C3_0 * vec3<f32>(6.0 * x * y, 3.0 * (xx - yy), 0.0);
            g[10] = C3_1 * vec3<f32>(y * z, x * z, x * y);
            g[11] = C3_2 * vec3<f32>(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z);
            g[12] = C3_3 * vec3<f32>(-6.0 * x * z, -6.0 * y * z, 3.0 * (2.0 * zz - xx - yy));
            g[13] = C3_4 * vec3<f32>(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z);
            g[14] = C3_5 * vec3<f32>(2.0 * x * z, -2.0 * y * z, xx - yy);
            g[15] = C3_6 * vec3<f32>(3.0 * (xx - yy), -6.0 * x * y, 0.0);
        }
    }
    return g;
}

fn load_dir(i: u32) -> vec3<f32> {
    return vec3<f32>(dirs[3u * i], dirs[3u * i + 1u], dirs[3u * i + 2u]);
}

fn load_coeff(i: u32, j: u32) -> vec3<f32> {
    let base = 3u * (i * K + j);
    return vec3<f32>(coeffs[base], coeffs[base + 1u], coeffs[base + 2u]);
}

// The colour before the clamp: sum_j coeffs_j Y_j + 0.5.
fn unclamped(i: u32, y: array<f32, 16>) -> vec3<f32> {
    var sum = vec3<f32>(0.5);
    for (var j = 0u; j < K; j++) {
        sum += y[j] * load_coeff(i, j);
    }
    return sum;
}
