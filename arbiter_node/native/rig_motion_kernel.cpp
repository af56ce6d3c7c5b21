// Native kernel of the general arbiter's per-frame rig-motion refinement:
// arbiter_node._rig_motion_kernel, under rig_motion_fit.refine_rig_motion (the numpy code
// there is the reference: the same residuals, steps and covariance in the same order).
//
// Why native: the refinement runs on every frame with a gyro (the gyro bias measured from
// the cameras' tracks, general_fusion) and the bench allows the IMU 5 % of a frame's CPU;
// numpy costs 1-3 ms a frame (vectorised or not), almost all of it call overhead on
// a few hundred tracks.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <Eigen/Dense>

#include <cmath>
#include <string>
#include <vector>

namespace py = pybind11;

namespace {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using Mat6 = Eigen::Matrix<double, 6, 6>;
using RowMat3 = Eigen::Matrix<double, 3, 3, Eigen::RowMajor>;
using Array = py::array_t<double, py::array::c_style | py::array::forcecast>;
using IndexArray = py::array_t<long long, py::array::c_style | py::array::forcecast>;

constexpr double kStep = 1e-7;      // forward-difference step of the Jacobian (as the numpy one)
constexpr double kTiny = 1e-30;     // keeps a zero Sampson gradient finite

void require(bool ok, const std::string& what) {
  if (!ok) throw py::value_error("refine_rig_motion: " + what);
}

// SO(3) exponential (Rodrigues).
Mat3 exp_so3(const Vec3& v) {
  const double a = v.norm();
  Mat3 K;
  K << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  if (a < 1e-12) return Mat3::Identity() + K;
  return Mat3::Identity() + std::sin(a) / a * K + (1.0 - std::cos(a)) / (a * a) * K * K;
}

Mat3 skew(const Vec3& v) {
  Mat3 K;
  K << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return K;
}

struct Problem {
  Mat3 R0;
  std::vector<Mat3> Rc;         // per camera: optical -> base_link
  std::vector<Vec3> centre;     // per camera: centre in base_link
  const long long* cam;         // per track: its camera
  const double* xa;             // (N, 2)
  const double* xb;             // (N, 2)
  const double* sigma;          // (N,)
  Eigen::Index n;
};

// Sampson residuals (in point stds) of all tracks for x = (rotation correction, t).
void residuals(const Problem& p, const Vec6& x, Eigen::VectorXd& r) {
  const Mat3 R = exp_so3(x.head<3>()) * p.R0;
  const Vec3 t = x.tail<3>();
  std::vector<Mat3> E(p.Rc.size());
  for (size_t k = 0; k < p.Rc.size(); ++k) {
    const Mat3& Rc = p.Rc[k];
    E[k] = skew(Rc.transpose() * (R * p.centre[k] + t - p.centre[k])) * (Rc.transpose() * R * Rc);
  }
  r.resize(p.n);
  for (Eigen::Index i = 0; i < p.n; ++i) {
    const Mat3& Ek = E[p.cam[i]];
    const Vec3 ha(p.xa[2 * i], p.xa[2 * i + 1], 1.0);
    const Vec3 hb(p.xb[2 * i], p.xb[2 * i + 1], 1.0);
    const Vec3 Exb = Ek * hb;
    const Vec3 Eta = Ek.transpose() * ha;
    const double grad2 = Exb.x() * Exb.x() + Exb.y() * Exb.y() + Eta.x() * Eta.x() + Eta.y() * Eta.y();
    r[i] = ha.dot(Exb) / (std::sqrt(grad2 + kTiny) * p.sigma[i]);
  }
}

void jacobian(const Problem& p, const Vec6& x, const Eigen::VectorXd& r0, Eigen::MatrixXd& J) {
  J.resize(p.n, 6);
  Eigen::VectorXd rk;
  for (int k = 0; k < 6; ++k) {
    Vec6 xk = x;
    xk[k] += kStep;
    residuals(p, xk, rk);
    J.col(k) = (rk - r0) / kStep;
  }
}

// -> (ok, R (3, 3), t (3,), covariance (6, 6), n_inliers, rms, reason)
py::tuple refine_rig_motion(const Array& R0, const Array& t0, const Array& cam_R, const Array& cam_centre,
                            const IndexArray& cam_index, const Array& xa, const Array& xb, const Array& sigma,
                            int iterations, double huber, double inlier_sigmas, int min_points) {
  require(R0.ndim() == 2 && R0.shape(0) == 3 && R0.shape(1) == 3, "R0 must be (3, 3)");
  require(t0.ndim() == 1 && t0.shape(0) == 3, "t0 must be (3,)");
  require(cam_R.ndim() == 3 && cam_R.shape(1) == 3 && cam_R.shape(2) == 3, "cam_R must be (K, 3, 3)");
  const py::ssize_t K = cam_R.shape(0);
  require(cam_centre.ndim() == 2 && cam_centre.shape(0) == K && cam_centre.shape(1) == 3,
          "cam_centre must be (K, 3) with K cameras as cam_R");
  require(xa.ndim() == 2 && xa.shape(1) == 2, "xa must be (N, 2)");
  const py::ssize_t N = xa.shape(0);
  require(xb.ndim() == 2 && xb.shape(0) == N && xb.shape(1) == 2, "xb must be (N, 2) as xa");
  require(sigma.ndim() == 1 && sigma.shape(0) == N, "sigma must be (N,) as xa");
  require(cam_index.ndim() == 1 && cam_index.shape(0) == N, "cam_index must be (N,) as xa");
  require(iterations >= 0, "iterations must be >= 0");
  require(huber > 0.0 && inlier_sigmas > 0.0, "huber and inlier_sigmas must be > 0");

  Problem p;
  p.R0 = Eigen::Map<const RowMat3>(R0.data());
  for (py::ssize_t k = 0; k < K; ++k) {
    p.Rc.emplace_back(Eigen::Map<const RowMat3>(cam_R.data() + 9 * k));
    p.centre.emplace_back(Eigen::Map<const Vec3>(cam_centre.data() + 3 * k));
  }
  p.cam = cam_index.data();
  for (py::ssize_t i = 0; i < N; ++i) require(p.cam[i] >= 0 && p.cam[i] < K, "cam_index out of range");
  for (py::ssize_t i = 0; i < N; ++i) require(sigma.data()[i] > 0.0, "sigma must be > 0");
  p.xa = xa.data();
  p.xb = xb.data();
  p.sigma = sigma.data();
  p.n = N;

  auto fail = [&](const std::string& reason) {
    return py::make_tuple(false, py::none(), py::none(), py::none(), 0, std::nan(""), reason);
  };
  if (N < min_points) return fail(std::to_string(N) + " tracks in both frames; need " + std::to_string(min_points));

  Vec6 x;
  x << 0, 0, 0, t0.data()[0], t0.data()[1], t0.data()[2];
  Eigen::VectorXd r, w;
  Eigen::MatrixXd J;
  for (int it = 0; it < iterations; ++it) {
    residuals(p, x, r);
    jacobian(p, x, r, J);
    // Huber weights: full below `huber` point stds, 1/|r| beyond
    w = r.cwiseAbs().unaryExpr([huber](double a) { return a <= huber ? 1.0 : huber / std::max(a, 1e-12); });
    const Mat6 A = J.transpose() * w.asDiagonal() * J + 1e-12 * Mat6::Identity();
    const Vec6 g = J.transpose() * w.cwiseProduct(r);
    // (as numpy's solve: LU with partial pivoting; a singular system shows as non-finite)
    x -= A.partialPivLu().solve(g);
    if (!x.allFinite()) return fail("not finite");
  }
  residuals(p, x, r);
  jacobian(p, x, r, J);
  std::vector<Eigen::Index> inl;
  double ss = 0.0;
  for (Eigen::Index i = 0; i < N; ++i)
    if (std::abs(r[i]) < inlier_sigmas) {
      inl.push_back(i);
      ss += r[i] * r[i];
    }
  const int n_in = static_cast<int>(inl.size());
  if (n_in < min_points) return fail(std::to_string(n_in) + " inliers; need " + std::to_string(min_points));
  const double rms = std::sqrt(ss / n_in);
  Mat6 JtJ = Mat6::Zero();
  for (Eigen::Index i : inl) JtJ.selfadjointView<Eigen::Lower>().rankUpdate(J.row(i).transpose());
  JtJ = JtJ.selfadjointView<Eigen::Lower>();
  // scaled by the residuals' own RMS: tracks are often better than their nominal std
  const Mat6 cov = JtJ.partialPivLu().inverse() * rms * rms;
  if (!cov.allFinite()) return fail("singular fit");

  const Mat3 R = exp_so3(x.head<3>()) * p.R0;
  py::array_t<double> R_out({3, 3}), t_out({3}), cov_out({6, 6});
  Eigen::Map<RowMat3>(R_out.mutable_data()) = R;
  Eigen::Map<Vec3>(t_out.mutable_data()) = x.tail<3>();
  Eigen::Map<Eigen::Matrix<double, 6, 6, Eigen::RowMajor>>(cov_out.mutable_data()) = cov;
  return py::make_tuple(true, R_out, t_out, cov_out, n_in, rms, std::string());
}

}  // namespace

PYBIND11_MODULE(_rig_motion_kernel, m) {
  m.doc() = "Native kernel of the general arbiter's rig-motion refinement (arbiter_node.rig_motion_fit).";
  m.def("refine_rig_motion", &refine_rig_motion, py::arg("R0"), py::arg("t0"), py::arg("cam_R"),
        py::arg("cam_centre"), py::arg("cam_index"), py::arg("xa"), py::arg("xb"), py::arg("sigma"),
        py::arg("iterations"), py::arg("huber"), py::arg("inlier_sigmas"), py::arg("min_points"),
        "Gauss-Newton (Huber weights) of the rig's motion on all tracks' Sampson errors from (R0, t0) "
        "-> (ok, R, t, covariance 6x6 of (rotation correction, t), n_inliers, rms, reason).");
}
