// Native kernel of the per-quarter estimator: camera_pose_nodes._quarter_kernels.
//
// Each function is one whole step of PoseEKF or LandmarkMap (pose_ekf.py, landmark_map.py)
// on numpy arrays, so that a frame costs a few calls instead of tens of thousands of small
// numpy ones. The numpy/filterpy code stays the reference: the same models, gates and checks
// in the same order; only the Kalman update is written in information form (O(N) in the
// number of features instead of inverting a 2N x 2N innovation covariance).
//
// Arrays come in as C-contiguous float64 (pybind11 converts anything else) and are read
// through row-major maps; computations use Eigen's fixed-size types.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <string>
#include <vector>

namespace py = pybind11;

namespace {

constexpr int kDim = 12;            // error state: p, dtheta, v, w
constexpr double kMinEig = 1e-12;   // pose_ekf._MIN_EIG
constexpr double kEps = 1e-6;       // pose_ekf._EPS: epipolar finite-difference step
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kPi = 3.14159265358979323846;

using Vec2 = Eigen::Vector2d;
using Vec3 = Eigen::Vector3d;
using Vec4 = Eigen::Vector4d;
using Mat2 = Eigen::Matrix2d;
using Mat3 = Eigen::Matrix3d;
using Mat4 = Eigen::Matrix4d;
using Mat6 = Eigen::Matrix<double, 6, 6>;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using Mat23 = Eigen::Matrix<double, 2, 3>;
using Vec12 = Eigen::Matrix<double, kDim, 1>;
using Mat12 = Eigen::Matrix<double, kDim, kDim>;
using Mat2x12 = Eigen::Matrix<double, 2, kDim>;
using Row12 = Eigen::Matrix<double, 1, kDim>;
template <int R, int C>
using RowMajor = Eigen::Matrix<double, R, C, Eigen::RowMajor>;

// Inputs: any array-like, converted to C-contiguous float64 by pybind11 if need be.
using Array = py::array_t<double, py::array::c_style | py::array::forcecast>;

// ----- numpy <-> Eigen -----------------------------------------------------------------------

std::string shape_text(const Array& a) {
  std::string s = "(";
  for (py::ssize_t i = 0; i < a.ndim(); ++i) s += (i ? ", " : "") + std::to_string(a.shape(i));
  return s + (a.ndim() == 1 ? ",)" : ")");
}

// Checks a's shape against `shape` (-1: any extent); the error names the argument.
void require_shape(const Array& a, const char* name, std::vector<py::ssize_t> shape) {
  bool ok = a.ndim() == static_cast<py::ssize_t>(shape.size());
  for (size_t i = 0; ok && i < shape.size(); ++i) ok = shape[i] < 0 || a.shape(i) == shape[i];
  if (!ok) {
    std::string want = "(";
    for (size_t i = 0; i < shape.size(); ++i)
      want += (i ? ", " : "") + (shape[i] < 0 ? std::string("N") : std::to_string(shape[i]));
    throw py::value_error(std::string(name) + ": expected shape " + want + (shape.size() == 1 ? ",)" : ")") +
                          ", got " + shape_text(a));
  }
}

void require_size(const Array& a, const char* name, py::ssize_t size) {
  if (a.size() != size)
    throw py::value_error(std::string(name) + ": expected " + std::to_string(size) + " numbers, got shape " +
                          shape_text(a));
}

// Measurement noise: the information form needs R invertible.
void require_positive(double v, const char* name) {
  if (!(v > 0.0 && std::isfinite(v)))
    throw py::value_error(std::string(name) + ": expected a positive noise sigma, got " + std::to_string(v));
}

template <int R, int C>
Eigen::Matrix<double, R, C> load(const double* p) {
  if constexpr (C == 1) return Eigen::Map<const Eigen::Matrix<double, R, 1>>(p);
  else return Eigen::Map<const RowMajor<R, C>>(p);
}

template <int R, int C>
void store(double* p, const Eigen::Matrix<double, R, C>& m) {
  if constexpr (C == 1) Eigen::Map<Eigen::Matrix<double, R, 1>>{p} = m;
  else Eigen::Map<RowMajor<R, C>>{p} = m;
}

py::array_t<double> new_array(std::vector<py::ssize_t> shape) { return py::array_t<double>(shape); }

py::array_t<bool> bool_array(const std::vector<char>& v) {
  py::array_t<bool> out(static_cast<py::ssize_t>(v.size()));
  bool* o = out.mutable_data();
  for (size_t i = 0; i < v.size(); ++i) o[i] = v[i] != 0;
  return out;
}

// ----- SO(3), as multicam_ego_motion.se3 ---------------------------------------------------------

// se3._quat_to_R: scipy's as_matrix of a unit quaternion, its operations in its order.
Mat3 quat_to_R(double qx, double qy, double qz, double qw) {
  const double x2 = qx * qx, y2 = qy * qy, z2 = qz * qz, w2 = qw * qw;
  const double xy = qx * qy, zw = qz * qw, xz = qx * qz, yw = qy * qw, yz = qy * qz, xw = qx * qw;
  Mat3 R;
  R << x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
       2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
       2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2;
  return R;
}

// se3.rotvec_to_R, the same operations in the same order: both kernels then fold
// bit-identical rotations into R_nom for the same dtheta.
Mat3 rotvec_to_R(const Vec3& v) {
  const double x = v[0], y = v[1], z = v[2];
  const double angle = std::sqrt(x * x + y * y + z * z);
  if (!std::isfinite(angle)) return Mat3::Constant(kNaN);
  double s;
  if (angle <= 1e-3) {   // scipy's series below 1e-3 rad
    const double a2 = angle * angle;
    s = 0.5 - a2 / 48 + a2 * a2 / 3840;
  } else {
    s = std::sin(angle / 2) / angle;
  }
  return quat_to_R(s * x, s * y, s * z, std::cos(angle / 2));
}

// se3.R_to_rotvec: closed form; near pi (where it loses precision) Eigen's quaternion path.
Vec3 R_to_rotvec(const Mat3& R) {
  const Vec3 v(0.5 * (R(2, 1) - R(1, 2)), 0.5 * (R(0, 2) - R(2, 0)), 0.5 * (R(1, 0) - R(0, 1)));
  const double sin = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  const double cos = 0.5 * (R(0, 0) + R(1, 1) + R(2, 2) - 1.0);
  const double angle = std::atan2(sin, cos);
  if (angle < 1e-8) return v;   // sin(angle) ~ angle
  if (angle > kPi - 1e-3) {
    const Eigen::AngleAxisd aa(R);
    return aa.angle() * aa.axis();
  }
  return v * (angle / sin);
}

Mat3 skew(const Vec3& v) {
  Mat3 K;
  K << 0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0;
  return K;
}

// ----- filter state ------------------------------------------------------------------------

struct Ekf {
  Vec12 x;
  Mat12 P;
  Mat3 R_nom;
};

Ekf load_state(const Array& x, const Array& P, const Array& R_nom) {
  require_size(x, "x", kDim);   // (12,) or filterpy's (12, 1)
  require_shape(P, "P", {kDim, kDim});
  require_shape(R_nom, "R_nom", {3, 3});
  return {load<kDim, 1>(x.data()), load<kDim, kDim>(P.data()), load<3, 3>(R_nom.data())};
}

py::tuple state_tuple(const Ekf& s) {
  auto x = new_array({kDim}), P = new_array({kDim, kDim}), R = new_array({3, 3});
  store(x.mutable_data(), s.x);
  store(P.mutable_data(), s.P);
  store(R.mutable_data(), s.R_nom);
  return py::make_tuple(x, P, R);
}

// PoseEKF._recentre: fold dtheta into R_nom, re-orthonormalised so that rounding never
// accumulates into a non-rotation (the polar factor U V^T of its SVD).
void recentre(Ekf& s) {
  const Vec3 dth = s.x.segment<3>(3);
  if ((dth.array() != 0.0).any()) {
    s.R_nom = rotvec_to_R(dth) * s.R_nom;
    if (s.R_nom.allFinite()) {
      Eigen::JacobiSVD<Mat3> svd(s.R_nom, Eigen::ComputeFullU | Eigen::ComputeFullV);
      s.R_nom = svd.matrixU() * svd.matrixV().transpose();
    }
    s.x.segment<3>(3).setZero();
  }
}

// PoseEKF._condition: keep P symmetric positive definite (rounding in long runs can break both).
void condition(Ekf& s) {
  Mat12 P = 0.5 * (s.P + s.P.transpose());
  Eigen::SelfAdjointEigenSolver<Mat12> eig(P);
  if (eig.info() == Eigen::Success && eig.eigenvalues().minCoeff() < kMinEig) {
    P = eig.eigenvectors() * eig.eigenvalues().cwiseMax(kMinEig).asDiagonal() * eig.eigenvectors().transpose();
    P = 0.5 * (P + P.transpose());
  }
  s.P = P;
}

// The Kalman update in information form, from the accepted measurements' information
// M = sum H^T R^-1 H and b = sum H^T R^-1 (z - h): P+ = (P^-1 + M)^-1, x+ = x + P+ b.
// Mathematically filterpy's update, at O(N) instead of inverting the 2N x 2N innovation
// covariance. P is factored rather than inverted (its condition number reaches 1e10 and more:
// a fused pose known to 1e-8 beside a twist of 1e2), so with P = L L^T,
// P+ = L (I + L^T M L)^-1 L^T, whose middle matrix has all eigenvalues >= 1.
// Returns false, the state untouched, if the result is not finite.
bool information_update(Ekf& s, const Mat12& M, const Vec12& b) {
  Mat12 L;
  Eigen::LLT<Mat12> chol(s.P);
  if (chol.info() == Eigen::Success) {
    L = chol.matrixL();
  } else {   // P at the edge of definiteness (rounding, a handed-over state): its square root
    Eigen::SelfAdjointEigenSolver<Mat12> eig(s.P);
    if (eig.info() != Eigen::Success) return false;
    L = eig.eigenvectors() * eig.eigenvalues().cwiseMax(0.0).cwiseSqrt().asDiagonal();
  }
  const Mat12 inner = Mat12::Identity() + L.transpose() * M * L;
  Eigen::LLT<Mat12> inner_chol(inner);
  if (inner_chol.info() != Eigen::Success) return false;
  const Mat12 W = inner_chol.matrixL().solve(L.transpose());   // P+ = W^T W
  const Mat12 P = W.transpose() * W;
  const Vec12 x = s.x + P * b;
  if (!x.allFinite() || !P.allFinite()) return false;
  s.x = x;
  s.P = P;
  return true;
}

// ----- predict -----------------------------------------------------------------------------

// PoseEKF.predict's constant-velocity model over dt (F and Q exactly as written there).
void predict(Ekf& s, double dt, double accel_sigma, double alpha_sigma) {
  const Mat3 I3 = Mat3::Identity();
  Mat12 F = Mat12::Identity();
  F.block<3, 3>(0, 6) = I3 * dt;
  // dtheta (odom) integrates the body rate rotated into odom: R_nom w dt
  F.block<3, 3>(3, 9) = s.R_nom * dt;
  const double qa = accel_sigma * accel_sigma, qw = alpha_sigma * alpha_sigma;
  const double dt2 = std::pow(dt, 2.0), dt3 = std::pow(dt, 3.0);
  Mat12 Q = Mat12::Zero();
  Q.block<3, 3>(0, 0) = I3 * (qa * dt3 / 3);
  Q.block<3, 3>(0, 6) = Q.block<3, 3>(6, 0) = I3 * (qa * dt2 / 2);
  Q.block<3, 3>(6, 6) = I3 * (qa * dt);
  Q.block<3, 3>(3, 3) = I3 * (qw * dt3 / 3);
  Q.block<3, 3>(3, 9) = s.R_nom * qw * dt2 / 2;
  Q.block<3, 3>(9, 3) = Q.block<3, 3>(3, 9).transpose();
  Q.block<3, 3>(9, 9) = I3 * (qw * dt);
  s.x = F * s.x;
  s.P = F * s.P * F.transpose() + Q;
  recentre(s);
  condition(s);
}

// ----- reprojection update -----------------------------------------------------------------

// One landmark through PoseEKF.project: normalized coordinates, camera-frame depth (|z| >=
// 1e-9, as projection_jacobian) and the Jacobians d(uv)/d(state) and d(uv)/dX.
struct Projection {
  Vec2 uv;
  double depth;
  Mat2x12 H;
  Mat23 J_X;
};

Projection project(const Mat3& A, const Vec3& cam_offset, const Vec3& p, const Vec3& X) {
  const Vec3 d = X - p;                  // landmark relative to body, odom
  const Vec3 Xc = A * d - cam_offset;    // A: odom -> camera; cam_offset = R_bc^T t_bc
  const double zs = std::abs(Xc[2]) < 1e-9 ? 1e-9 : Xc[2];
  Projection out;
  out.uv = Xc.head<2>() / zs;
  out.depth = zs;
  Mat23 Jpi;
  Jpi << 1.0 / zs, 0.0, -out.uv[0] / zs, 0.0, 1.0 / zs, -out.uv[1] / zs;
  // Xc = A (I - [dtheta]x)(X - p) - ...: dXc/dp = -A, dXc/ddtheta = A [X - p]x
  out.J_X = Jpi * A;
  out.H.setZero();
  out.H.block<2, 3>(0, 0) = -out.J_X;
  out.H.block<2, 3>(0, 3) = Jpi * (A * skew(d));
  return out;
}

// PoseEKF.update: each feature gated on its 2-dof Mahalanobis distance against the prior
// (depth > min_depth, finite residual, det(S) > 0, d2 < gate_chi2), then one update with the
// accepted ones, R block-diagonal: diag(sigma^2) + J_X C_X J_X^T per feature.
py::tuple ekf_update_reprojection(const Array& x, const Array& P, const Array& R_nom, const Array& X,
                                  const Array& z, double sigma_u, double sigma_v, const Array& T_base_cam,
                                  double gate_chi2, double min_depth, const std::optional<Array>& X_cov) {
  Ekf s = load_state(x, P, R_nom);
  require_shape(X, "X", {-1, 3});
  const py::ssize_t n = X.shape(0);
  require_shape(z, "z", {n, 2});
  require_shape(T_base_cam, "T_base_cam", {4, 4});
  if (X_cov) require_shape(*X_cov, "X_cov", {n, 3, 3});
  require_positive(sigma_u, "sigma_u");
  require_positive(sigma_v, "sigma_v");
  const Mat4 T_bc = load<4, 4>(T_base_cam.data());
  const double* Xd = X.data();
  const double* zd = z.data();
  const double* Cd = X_cov ? X_cov->data() : nullptr;
  std::vector<char> inliers(static_cast<size_t>(n), 0);
  bool ok = true;
  {
    py::gil_scoped_release unlocked;
    const Mat3 R_bc = T_bc.block<3, 3>(0, 0);
    const Vec3 cam_offset = R_bc.transpose() * T_bc.block<3, 1>(0, 3);
    const Mat3 A = (s.R_nom * R_bc).transpose();
    const Vec3 p = s.x.head<3>();
    Mat2 R0 = Mat2::Zero();
    R0(0, 0) = sigma_u * sigma_u;
    R0(1, 1) = sigma_v * sigma_v;
    Mat12 M = Mat12::Zero();
    Vec12 b = Vec12::Zero();
    bool any = false;
    for (py::ssize_t i = 0; i < n; ++i) {
      const Projection f = project(A, cam_offset, p, load<3, 1>(Xd + 3 * i));
      const Vec2 r = load<2, 1>(zd + 2 * i) - f.uv;
      Mat2 Rm = R0;
      if (Cd) Rm += f.J_X * load<3, 3>(Cd + 9 * i) * f.J_X.transpose();
      const Mat2 S = f.H * s.P * f.H.transpose() + Rm;
      const double det = S.determinant();
      if (!(f.depth > min_depth && r.allFinite() && det > 0.0)) continue;
      if (!(r.dot(S.inverse() * r) < gate_chi2)) continue;
      Eigen::LLT<Mat2> noise(Rm);
      const Mat2 Rinv = noise.solve(Mat2::Identity());
      if (noise.info() != Eigen::Success || !Rinv.allFinite()) {
        ok = false;   // an indefinite landmark covariance: no update, as if not finite
        break;
      }
      const Eigen::Matrix<double, kDim, 2> HtRinv = f.H.transpose() * Rinv;
      M.noalias() += HtRinv * f.H;
      b.noalias() += HtRinv * r;
      inliers[static_cast<size_t>(i)] = 1;
      any = true;
    }
    if (ok && any) ok = information_update(s, M, b);
    if (!ok) {   // a degenerate geometry produced NaN: the prediction is kept, no inliers
      std::fill(inliers.begin(), inliers.end(), 0);
    } else if (any) {
      recentre(s);
      condition(s);
    }
  }
  py::tuple st = state_tuple(s);
  return py::make_tuple(st[0], st[1], st[2], bool_array(inliers), ok);
}

// ----- epipolar update ---------------------------------------------------------------------

// pose_ekf._epipolar_normal: the epipolar plane's normal in the camera frame, (c1 - c2) x r1.
Vec3 epipolar_normal(const Vec3& c1, const Vec3& c2, const Mat3& A, const Vec3& r1_cam) {
  return (A * (c1 - c2)).cross(r1_cam);
}

// pose_ekf._line_distance: signed distance of xy2 from the line n (normalized units).
double line_distance(const Vec3& n, const Vec2& xy2) {
  return (n[0] * xy2[0] + n[1] * xy2[1] + n[2]) / std::max(std::hypot(n[0], n[1]), 1e-12);
}

// PoseEKF.update_epipolar: the same residual, the same numerical Jacobian (steps of 1e-6 on
// position, and on rotation as rotvec_to_R(eps e_k) R_nom), the same gates and baseline test,
// then one update with R = sigma^2 I.
py::tuple ekf_update_epipolar(const Array& x, const Array& P, const Array& R_nom, const Array& c1,
                              const Array& r1, const Array& xy2, double sigma, const Array& T_base_cam,
                              double gate_chi2, double min_baseline) {
  Ekf s = load_state(x, P, R_nom);
  require_shape(c1, "c1", {-1, 3});
  const py::ssize_t n = c1.shape(0);
  require_shape(r1, "r1", {n, 3});
  require_shape(xy2, "xy2", {n, 2});
  require_shape(T_base_cam, "T_base_cam", {4, 4});
  require_positive(sigma, "sigma");
  const Mat4 T_bc = load<4, 4>(T_base_cam.data());
  const double *c1d = c1.data(), *r1d = r1.data(), *xyd = xy2.data();
  std::vector<char> inliers(static_cast<size_t>(n), 0);
  bool ok = true;
  {
    py::gil_scoped_release unlocked;
    const Mat3 R_bc = T_bc.block<3, 3>(0, 0);
    const Vec3 t_bc = T_bc.block<3, 1>(0, 3);
    const Vec3 p = s.x.head<3>();
    const Vec3 lever = s.R_nom * t_bc;
    const Vec3 c2 = p + lever;
    const Mat3 A = (s.R_nom * R_bc).transpose();   // odom -> camera
    // The perturbed poses of the numerical Jacobian, shared by all features. A position step
    // leaves the camera's rotation, hence the ray in the camera frame, unchanged.
    Mat3 A_rot[3];
    Vec3 c2_pos[3], c2_rot[3];
    for (int k = 0; k < 3; ++k) {
      const Vec3 step = Vec3::Unit(k) * kEps;
      c2_pos[k] = (p + step) + lever;
      const Mat3 R_ob = rotvec_to_R(step) * s.R_nom;
      A_rot[k] = (R_ob * R_bc).transpose();
      c2_rot[k] = p + R_ob * t_bc;
    }
    const double sigma2 = sigma * sigma;
    Mat12 M = Mat12::Zero();
    Vec12 b = Vec12::Zero();
    bool any = false;
    for (py::ssize_t i = 0; i < n; ++i) {
      const Vec3 c = load<3, 1>(c1d + 3 * i);
      // a short baseline leaves the epipolar line undefined (pure rotation, standing still)
      const Vec3 base = c - c2;
      if (!(std::sqrt(base[0] * base[0] + base[1] * base[1] + base[2] * base[2]) >= min_baseline)) continue;
      const Vec3 ray = load<3, 1>(r1d + 3 * i);
      const Vec2 xy = load<2, 1>(xyd + 2 * i);
      const Vec3 r1_cam = A * ray;
      const Vec3 nrm = epipolar_normal(c, c2, A, r1_cam);
      const double e = line_distance(nrm, xy);
      const double nxy = std::hypot(nrm[0], nrm[1]);
      const double sharp =
          nxy / std::max(std::sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]), 1e-12);
      if (!(std::isfinite(e) && sharp > 0.1)) continue;   // near the epipole the line is undefined
      Row12 h = Row12::Zero();
      for (int k = 0; k < 3; ++k) {
        h[k] = (line_distance(epipolar_normal(c, c2_pos[k], A, r1_cam), xy) - e) / kEps;
        h[3 + k] = (line_distance(epipolar_normal(c, c2_rot[k], A_rot[k], A_rot[k] * ray), xy) - e) / kEps;
      }
      if (!h.allFinite()) continue;
      const double S = (h * s.P).dot(h) + sigma2;
      if (!(e * e < gate_chi2 * S)) continue;
      M.noalias() += h.transpose() * h / sigma2;
      b.noalias() += h.transpose() * (-e / sigma2);   // z = 0, h(x) = e
      inliers[static_cast<size_t>(i)] = 1;
      any = true;
    }
    if (any) {
      ok = information_update(s, M, b);
      if (ok) {
        recentre(s);
        condition(s);
      } else {   // keep the prediction, no inliers
        std::fill(inliers.begin(), inliers.end(), 0);
      }
    }
  }
  py::tuple st = state_tuple(s);
  return py::make_tuple(st[0], st[1], st[2], bool_array(inliers), ok);
}

// ----- realign to the fused pose ---------------------------------------------------------------

// PoseEKF.set_pose: the pose marginal replaced by N(T, cov6), the twist moved along through
// the prior's pose-twist correlation (Gaussian conditioning): G = P_tp (P_pp + 1e-12 I)^-1,
// zeros if that is singular or not finite.
py::tuple ekf_set_pose(const Array& x, const Array& P, const Array& R_nom, const Array& T, const Array& cov6) {
  Ekf s = load_state(x, P, R_nom);
  require_shape(T, "T", {4, 4});
  require_shape(cov6, "cov6", {6, 6});
  const Mat4 Tm = load<4, 4>(T.data());
  const Mat6 C_in = load<6, 6>(cov6.data());
  {
    py::gil_scoped_release unlocked;
    const Mat6 C = 0.5 * (C_in + C_in.transpose());
    const Mat3 R_new = Tm.block<3, 3>(0, 0);
    const Vec3 p_new = Tm.block<3, 1>(0, 3);
    Vec6 delta;
    delta << p_new - s.x.head<3>(), R_to_rotvec(R_new * s.R_nom.transpose());
    const Mat6 Ppp = s.P.topLeftCorner<6, 6>();
    const Mat6 Ptp = s.P.bottomLeftCorner<6, 6>();
    // G^T = solve(P_pp + 1e-12 I, P_tp^T), LU with partial pivoting as numpy's solve
    Mat6 G = (Ppp + Mat6::Identity() * kMinEig).partialPivLu().solve(Ptp.transpose()).transpose();
    if (!G.allFinite()) G.setZero();
    const Mat6 GC = G * C;
    Mat12 Pn;
    Pn.topLeftCorner<6, 6>() = C;
    Pn.bottomLeftCorner<6, 6>() = GC;
    Pn.topRightCorner<6, 6>() = GC.transpose();
    Pn.bottomRightCorner<6, 6>() = s.P.bottomRightCorner<6, 6>() - G * Ptp.transpose() + GC * G.transpose();
    s.x.tail<6>() = s.x.tail<6>() + G * delta;
    s.x.head<3>() = p_new;
    s.x.segment<3>(3).setZero();
    s.R_nom = R_new;
    s.P = Pn;
    condition(s);
  }
  return state_tuple(s);
}

py::tuple ekf_predict(const Array& x, const Array& P, const Array& R_nom, double dt, double accel_sigma,
                      double alpha_sigma) {
  Ekf s = load_state(x, P, R_nom);
  {
    py::gil_scoped_release unlocked;
    predict(s, dt, accel_sigma, alpha_sigma);
  }
  return state_tuple(s);
}

// ----- triangulation -------------------------------------------------------------------------

// landmark_map.triangulate_views for one point: linear DLT relative to the first camera
// centre (conditioning), the smallest right singular vector of the 2V x 4 system.
Vec3 triangulate_point(const double* R_oc, const double* c_o, const double* xy, int V) {
  const Vec3 ref = load<3, 1>(c_o);
  Eigen::Matrix<double, Eigen::Dynamic, 4> A(2 * V, 4);
  for (int v = 0; v < V; ++v) {
    const Mat3 Rt = load<3, 3>(R_oc + 9 * v).transpose();   // odom -> camera
    RowMajor<3, 4> Pv;
    Pv << Rt, -(Rt * (load<3, 1>(c_o + 3 * v) - ref));
    A.row(v) = xy[2 * v] * Pv.row(2) - Pv.row(0);
    A.row(V + v) = xy[2 * v + 1] * Pv.row(2) - Pv.row(1);
  }
  if (!A.allFinite()) return Vec3::Constant(kNaN);
  Eigen::JacobiSVD<Eigen::Matrix<double, Eigen::Dynamic, 4>> svd(A, Eigen::ComputeFullV);
  const Vec4 Xh = svd.matrixV().col(3);
  const double w = std::abs(Xh[3]) < 1e-12 ? 1e-12 : Xh[3];
  return Xh.head<3>() / w + ref;
}

// landmark_map.angle_deg: a zero-length ray counts as no parallax.
double angle_deg(const Vec3& a, const Vec3& b) {
  const double n = a.norm() * b.norm();
  double c = n > 1e-300 ? a.dot(b) / std::max(n, 1e-300) : 1.0;
  c = std::clamp(c, -1.0, 1.0);
  return std::acos(c) * (180.0 / kPi);
}

struct Triangulation {
  double sigma_n, min_depth, max_depth, parallax_deg, focal_px, max_reproj_px;
};

// LandmarkMap.triangulate's checks and landmark_map.triangulation_covariance for one point:
// finite, depth in (min, max) in every view, parallax at the point between the first and
// last view, reprojection error (px) in every view; the covariance
// (sum_v w_v J_v^T J_v / sigma_n^2 + 1e-12 I)^-1 of the accepted.
bool check_point(const Triangulation& cfg, const Vec3& X, const double* R_oc, const double* c_o,
                 const double* xy, const double* weights, int V, double& parallax, Mat3& C) {
  std::vector<Vec3> rel(V), Xc(V);
  for (int v = 0; v < V; ++v) {
    rel[v] = X - load<3, 1>(c_o + 3 * v);
    Xc[v] = load<3, 3>(R_oc + 9 * v).transpose() * rel[v];
  }
  parallax = angle_deg(rel[0], rel[V - 1]);
  bool ok = X.allFinite();
  for (int v = 0; v < V; ++v) ok = ok && Xc[v][2] > cfg.min_depth && Xc[v][2] < cfg.max_depth;
  ok = ok && parallax >= cfg.parallax_deg;
  for (int v = 0; ok && v < V; ++v) {
    const double zs = Xc[v][2] > 1e-9 ? Xc[v][2] : 1e-9;
    const Vec2 d = Xc[v].head<2>() / zs - load<2, 1>(xy + 2 * v);
    ok = std::sqrt(d[0] * d[0] + d[1] * d[1]) * cfg.focal_px < cfg.max_reproj_px;
  }
  if (!ok) return false;
  // a point seen over a short baseline is known far worse along its ray than across it
  Mat3 info = Mat3::Zero();
  for (int v = 0; v < V; ++v) {
    const double zs = std::abs(Xc[v][2]) < 1e-9 ? 1e-9 : Xc[v][2];
    Mat23 Jpi;
    Jpi << 1.0 / zs, 0.0, -(Xc[v][0] / zs) / zs, 0.0, 1.0 / zs, -(Xc[v][1] / zs) / zs;
    const Mat23 J = Jpi * load<3, 3>(R_oc + 9 * v).transpose();   // d(xy)/dX
    info.noalias() += weights[v] * (J.transpose() * J);
  }
  info /= cfg.sigma_n * cfg.sigma_n;
  // a tiny ridge keeps a degenerate (rotation-only) point invertible
  C = (info + Mat3::Identity() * 1e-12).ldlt().solve(Mat3::Identity());
  return true;
}

py::tuple triangulate_checked(const Array& R_oc, const Array& c_o, const Array& xy, const Array& view_weights,
                              double sigma_n, double min_depth, double max_depth, double parallax_deg,
                              double focal_px, double max_reproj_px) {
  require_shape(R_oc, "R_oc", {-1, -1, 3, 3});
  const py::ssize_t n = R_oc.shape(0), V = R_oc.shape(1);
  if (V < 1) throw py::value_error("R_oc: needs at least one view per point");
  require_shape(c_o, "c_o", {n, V, 3});
  require_shape(xy, "xy", {n, V, 2});
  require_shape(view_weights, "view_weights", {n, V});
  const Triangulation cfg{sigma_n, min_depth, max_depth, parallax_deg, focal_px, max_reproj_px};
  auto X_out = new_array({n, 3}), C_out = new_array({n, 3, 3}), par_out = new_array({n});
  double *Xo = X_out.mutable_data(), *Co = C_out.mutable_data(), *po = par_out.mutable_data();
  const double *Rd = R_oc.data(), *cd = c_o.data(), *xyd = xy.data(), *wd = view_weights.data();
  std::vector<char> ok(static_cast<size_t>(n), 0);
  {
    py::gil_scoped_release unlocked;
    const int v = static_cast<int>(V);
    for (py::ssize_t i = 0; i < n; ++i) {
      const double *R = Rd + 9 * V * i, *c = cd + 3 * V * i, *q = xyd + 2 * V * i;
      const Vec3 X = triangulate_point(R, c, q, v);
      Mat3 C = Mat3::Constant(kNaN);   // only the accepted points get one
      double parallax;
      ok[static_cast<size_t>(i)] = check_point(cfg, X, R, c, q, wd + V * i, v, parallax, C);
      store(Xo + 3 * i, X);
      store(Co + 9 * i, C);
      po[i] = parallax;
    }
  }
  return py::make_tuple(X_out, C_out, par_out, bool_array(ok));
}

}  // namespace

PYBIND11_MODULE(_quarter_kernels, m) {
  m.doc() =
      "Native kernel of the per-quarter estimator (camera_pose_nodes.kernel selects it): each "
      "function is one whole step of PoseEKF or LandmarkMap on numpy arrays. The filter state "
      "(x (12,), P (12, 12), R_nom (3, 3)) goes in and comes back as new arrays.";
  m.def("ekf_predict", &ekf_predict, py::arg("x"), py::arg("P"), py::arg("R_nom"), py::arg("dt"),
        py::arg("accel_sigma"), py::arg("alpha_sigma"),
        "PoseEKF.predict over dt (> 0), re-centred and conditioned -> (x, P, R_nom).");
  m.def("ekf_update_reprojection", &ekf_update_reprojection, py::arg("x"), py::arg("P"), py::arg("R_nom"),
        py::arg("X"), py::arg("z"), py::arg("sigma_u"), py::arg("sigma_v"), py::arg("T_base_cam"),
        py::arg("gate_chi2"), py::arg("min_depth"), py::arg("X_cov") = py::none(),
        "PoseEKF.update of landmarks X (N, 3) observed at z (N, 2) -> (x, P, R_nom, inliers (N,), ok). "
        "ok is False (prediction kept, no inliers) when the update was not finite.");
  m.def("ekf_update_epipolar", &ekf_update_epipolar, py::arg("x"), py::arg("P"), py::arg("R_nom"),
        py::arg("c1"), py::arg("r1"), py::arg("xy2"), py::arg("sigma"), py::arg("T_base_cam"),
        py::arg("gate_chi2"), py::arg("min_baseline"),
        "PoseEKF.update_epipolar -> (x, P, R_nom, inliers (N,), ok). "
        "ok is False (prediction kept, no inliers) when the update was not finite.");
  m.def("ekf_set_pose", &ekf_set_pose, py::arg("x"), py::arg("P"), py::arg("R_nom"), py::arg("T"),
        py::arg("cov6"), "PoseEKF.set_pose to the fused pose N(T, cov6) -> (x, P, R_nom).");
  m.def("triangulate_checked", &triangulate_checked, py::arg("R_oc"), py::arg("c_o"), py::arg("xy"),
        py::arg("view_weights"), py::arg("sigma_n"), py::arg("min_depth"), py::arg("max_depth"),
        py::arg("parallax_deg"), py::arg("focal_px"), py::arg("max_reproj_px"),
        "triangulate_views + LandmarkMap.triangulate's checks + triangulation_covariance -> "
        "(X (N, 3), C (N, 3, 3), parallax (N,), ok (N,)); C is NaN where not ok.");
}
