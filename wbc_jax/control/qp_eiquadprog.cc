// The force QP  min 1/2 x'Hx + g'x  s.t.  Cx <= b  solved by eiquadprog (the dual active-set method
// of Goldfarb and Idnani, the QP solver of TSID's controller) inside an XLA program on the CPU,
// problem after problem of a batch. Built and registered by wbc_jax/control/qp_eiquadprog.py; the
// outputs are those of wbc_jax/control/qp_active_set_kernel.py (the same method as a Warp kernel):
// x, the multipliers (0 off the active set), the slacks b - Cx (floored at float32's smallest
// positive number), flags (converged, finite, eiquadprog's iterations that added a row) and stats (violation, KKT residual
// and its dual, primal and complementarity parts), all of the problem scaled as
// wbc_jax.control.qp_ipm.interior_point scales it (rows of C to unit norm or to their weight,
// max|H| = 1, data to O(1)). Solved in double precision whatever the inputs' type.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include <Eigen/Dense>

#include "eiquadprog/eiquadprog-fast.hpp"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

using eiquadprog::solvers::EiquadprogFast;
using Eigen::MatrixXd;
using Eigen::VectorXd;

constexpr double kTiny = 1.1754943508222875e-38;  // float32's smallest normal number

template <typename T>
ffi::Error SolveAll(const T* H, const T* g, const T* C, const T* b, const T* weight, bool weighted,
                    int64_t batch, int64_t n, int64_t m, double tol, T* x_out, T* lam_out, T* s_out,
                    int32_t* flags_out, T* stats_out) {
  // One solver per thread, resized only when the problem's shape changes (its reset allocates).
  thread_local EiquadprogFast solver;
  thread_local int64_t solver_n = -1, solver_m = -1;
  if (solver_n != n || solver_m != m) {
    solver.reset(n, 0, m);
    solver_n = n;
    solver_m = m;
  }
  MatrixXd Hs(n, n), CE(0, n), CI(m, n);
  VectorXd gs(n), ce0(0), ci0(m), x(n), row(m), lam(m);
  for (int64_t p = 0; p < batch; ++p) {
    const T* Hp = H + p * n * n;
    const T* gp = g + p * n;
    const T* Cp = C + p * m * n;
    const T* bp = b + p * m;
    bool finite = true;
    // Scaling (qp_ipm.interior_point's).
    for (int64_t k = 0; k < m; ++k) {
      double nrm = 0.0;
      for (int64_t j = 0; j < n; ++j) {
        const double c = Cp[k * n + j];
        nrm += c * c;
        finite = finite && std::isfinite(c);
      }
      nrm = std::sqrt(nrm);
      if (!(nrm > 0.0)) nrm = 1.0;
      if (weighted) nrm /= static_cast<double>(weight[p * m + k]);
      row[k] = nrm;
      finite = finite && std::isfinite(static_cast<double>(bp[k]));
    }
    double h = 0.0;
    for (int64_t i = 0; i < n * n; ++i) {
      h = std::max(h, std::abs(static_cast<double>(Hp[i])));
      finite = finite && std::isfinite(static_cast<double>(Hp[i]));
    }
    if (!(h > 0.0) || !std::isfinite(h)) h = 1.0;
    double data = 0.0;
    for (int64_t i = 0; i < n; ++i) {
      gs[i] = static_cast<double>(gp[i]) / h;
      data = std::max(data, std::abs(gs[i]));
      finite = finite && std::isfinite(gs[i]);
    }
    for (int64_t k = 0; k < m; ++k) data = std::max(data, std::abs(static_cast<double>(bp[k]) / row[k]));
    if (!(data > 0.0) || !std::isfinite(data)) data = 1.0;
    gs /= data;
    for (int64_t i = 0; i < n; ++i)
      for (int64_t j = 0; j < n; ++j)
        Hs(i, j) = 0.5 * (static_cast<double>(Hp[i * n + j]) + static_cast<double>(Hp[j * n + i])) / h;
    // eiquadprog's form: CI x + ci0 >= 0, i.e. -C_k x / row_k + b_k / (row_k data) >= 0.
    for (int64_t k = 0; k < m; ++k) {
      for (int64_t j = 0; j < n; ++j) CI(k, j) = -static_cast<double>(Cp[k * n + j]) / row[k];
      ci0[k] = static_cast<double>(bp[k]) / (row[k] * data);
    }
    bool solved = false;
    int steps = 0;
    lam.setZero();
    x.setZero();
    if (finite) {
      const auto status = solver.solve_quadprog(Hs, gs, CE, ce0, CI, ci0, x);
      solved = status == eiquadprog::solvers::EIQUADPROG_FAST_OPTIMAL;
      steps = std::max(solver.getIteratios() - 1, 0);  // its last iteration finds no violated row
      const auto& active = solver.getActiveSet();
      const auto& u = solver.getLagrangeMultipliers();
      for (size_t a = 0; a < solver.getActiveSetSize(); ++a) {
        const int k = active[a];
        if (k >= 0 && k < m) lam[k] = std::max(u[a], 0.0);
      }
      finite = x.allFinite();
    }
    // The KKT residual of the scaled problem (qp_ipm's residuals' definitions).
    const VectorXd Hx = Hs * x;
    const VectorXd Cz = -CI.transpose() * lam;
    const double max_x = x.cwiseAbs().maxCoeff();
    const double res_d = (Hx + gs + Cz).cwiseAbs().maxCoeff() / (1.0 + std::max(Hx.cwiseAbs().maxCoeff(),
                                                                                  Cz.cwiseAbs().maxCoeff()));
    const VectorXd slack = CI * x + ci0;  // b - Cx, scaled
    const double violation = std::max(0.0, -slack.minCoeff());
    const double res_p = violation / (1.0 + (CI * x).cwiseAbs().maxCoeff());
    const double max_lam = lam.maxCoeff();
    double res_c = 0.0;
    for (int64_t k = 0; k < m; ++k)
      res_c = std::max(res_c, std::min(std::max(slack[k], 0.0) / (1.0 + max_x), lam[k] / (1.0 + max_lam)));
    const double res = std::max(std::max(res_d, res_p), res_c);
    const bool converged = finite && solved && violation <= tol;
    for (int64_t i = 0; i < n; ++i)
      x_out[p * n + i] = finite ? static_cast<T>(data * x[i]) : std::numeric_limits<T>::quiet_NaN();
    for (int64_t k = 0; k < m; ++k) {
      lam_out[p * m + k] = static_cast<T>(h * data * lam[k] / row[k]);
      s_out[p * m + k] = static_cast<T>(std::max(row[k] * data * slack[k], kTiny));
    }
    flags_out[p * 3 + 0] = converged ? 1 : 0;
    flags_out[p * 3 + 1] = finite ? 1 : 0;
    flags_out[p * 3 + 2] = steps;
    stats_out[p * 5 + 0] = static_cast<T>(finite ? violation / (1.0 + max_x) : INFINITY);
    stats_out[p * 5 + 1] = static_cast<T>(res);
    stats_out[p * 5 + 2] = static_cast<T>(res_d);
    stats_out[p * 5 + 3] = static_cast<T>(res_p);
    stats_out[p * 5 + 4] = static_cast<T>(res_c);
  }
  return ffi::Error::Success();
}

ffi::Error Solve(ffi::AnyBuffer H, ffi::AnyBuffer g, ffi::AnyBuffer C, ffi::AnyBuffer b, ffi::AnyBuffer weight,
                 double tol, bool weighted, ffi::Result<ffi::AnyBuffer> x, ffi::Result<ffi::AnyBuffer> lam,
                 ffi::Result<ffi::AnyBuffer> s, ffi::Result<ffi::Buffer<ffi::S32>> flags,
                 ffi::Result<ffi::AnyBuffer> stats) {
  const auto dims = C.dimensions();  // (batch..., m, n)
  if (dims.size() < 2) return ffi::Error::InvalidArgument("qp_eiquadprog: C must be (..., m, n)");
  const int64_t m = dims[dims.size() - 2], n = dims[dims.size() - 1];
  const int64_t batch = (m * n) ? static_cast<int64_t>(C.element_count()) / (m * n) : 0;
  const auto type = H.element_type();
  if (type == ffi::F64) {
    return SolveAll<double>(H.typed_data<double>(), g.typed_data<double>(), C.typed_data<double>(),
                            b.typed_data<double>(), weight.typed_data<double>(), weighted, batch, n, m, tol,
                            x->typed_data<double>(), lam->typed_data<double>(), s->typed_data<double>(),
                            flags->typed_data(), stats->typed_data<double>());
  }
  if (type == ffi::F32) {
    return SolveAll<float>(H.typed_data<float>(), g.typed_data<float>(), C.typed_data<float>(),
                           b.typed_data<float>(), weight.typed_data<float>(), weighted, batch, n, m, tol,
                           x->typed_data<float>(), lam->typed_data<float>(), s->typed_data<float>(),
                           flags->typed_data(), stats->typed_data<float>());
  }
  return ffi::Error::InvalidArgument("qp_eiquadprog: float32 or float64 data");
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(WbcEiquadprogSolve, Solve,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Attr<double>("tol")
                                  .Attr<bool>("weighted")
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::AnyBuffer>());
