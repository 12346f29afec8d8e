// C MuJoCo called from inside an XLA program through XLA's FFI (jax.ffi): the physics of one
// control tick of the closed loop and the contact slots after it, and that tick with the controller's
// dynamics terms from C MuJoCo (mj_step split at mj_step1), for wbc_jax.sim.host_scan.
// Built and registered by wbc_jax/sim/native.py; the semantics are those of
// wbc_jax.sim.physics.HostBatch.step and .contacts, environment by environment.
//
// Each environment is a C MuJoCo model and data owned by the Python caller, named by their
// addresses: handles (B, 4) uint32 = (model low, model high, data low, data high) 32-bit halves
// (a 64-bit integer array needs JAX's x64 mode).

#include <time.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <vector>

#include <mujoco/mujoco.h>

#include "xla/ffi/api/ffi.h"

#if defined(__x86_64__) || defined(__i386__)
#include <xmmintrin.h>
#endif

namespace ffi = xla::ffi;

namespace {

// XLA's threads flush denormals to zero (FTZ/DAZ); C MuJoCo runs in the default floating-point
// mode of a Python thread, so its steps equal HostBatch's bit for bit.
class DefaultFloatMode {
 public:
#if defined(__x86_64__) || defined(__i386__)
  DefaultFloatMode() : saved_(_mm_getcsr()) { _mm_setcsr(saved_ & ~(0x8000u | 0x0040u)); }
  ~DefaultFloatMode() { _mm_setcsr(saved_); }

 private:
  unsigned int saved_;
#endif
};

// CPU time of the calling threads inside the physics (C MuJoCo's steps and their checks) and the
// ticks stepped, since the last reset: what a tick's physics costs inside the closed loop.
std::atomic<int64_t> physics_ns{0};
std::atomic<int64_t> physics_ticks{0};

int64_t ThreadCpuNs() {
  timespec t;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return int64_t(t.tv_sec) * 1000000000 + t.tv_nsec;
}

struct Env {
  const mjModel* m;
  mjData* d;
};

Env EnvAt(const uint32_t* h, int64_t i) {
  auto address = [&](int j) { return (uint64_t(h[4 * i + j + 1]) << 32) | uint64_t(h[4 * i + j]); };
  return {reinterpret_cast<const mjModel*>(address(0)), reinterpret_cast<mjData*>(address(2))};
}

// wbc_jax.sim.physics.state_ok: finite positions, every speed below max_speed (a NaN speed fails).
bool StateOk(const mjModel* m, const mjData* d, double max_speed) {
  for (int i = 0; i < m->nq; ++i) {
    if (!std::isfinite(d->qpos[i])) return false;
  }
  for (int i = 0; i < m->nv; ++i) {
    if (!(std::fabs(d->qvel[i]) < max_speed)) return false;
  }
  return true;
}

// One environment, one tick: n_sub steps with ctrl held and the step's body wrenches; a state
// that becomes unsound is restored to the tick's start and flagged (ok false: frozen after).
// split: the data hold mj_step1 of the current state (WbcMujocoStepTerms), so the first step is
// its mj_step2 and each later one mj_step1 + mj_step2 (with the Euler integrator exactly mj_step).
// Returns whether the environment stepped (its contacts are then those of its data).
template <typename T>
bool StepEnv(Env e, const T* ctrl, const T* xfrc, int64_t n_sub, bool split, double max_speed, bool& ok,
             std::vector<mjtNum>& saved) {
  const mjModel* m = e.m;
  mjData* d = e.d;
  if (ok) {
    bool ctrl_ok = true;
    for (int i = 0; i < m->nu; ++i) ctrl_ok = ctrl_ok && std::isfinite(static_cast<double>(ctrl[i]));
    ok = ctrl_ok && StateOk(m, d, max_speed);
  }
  if (!ok) return false;
  const int nq = m->nq, nv = m->nv, nb6 = 6 * m->nbody;
  saved.resize(1 + nq + 2 * nv);
  saved[0] = d->time;
  std::copy(d->qpos, d->qpos + nq, saved.begin() + 1);
  std::copy(d->qvel, d->qvel + nv, saved.begin() + 1 + nq);
  std::copy(d->qacc_warmstart, d->qacc_warmstart + nv, saved.begin() + 1 + nq + nv);
  for (int i = 0; i < m->nu; ++i) d->ctrl[i] = static_cast<mjtNum>(ctrl[i]);
  for (int64_t s = 0; s < n_sub; ++s) {
    for (int j = 0; j < nb6; ++j) d->xfrc_applied[j] = static_cast<mjtNum>(xfrc[s * nb6 + j]);
    if (!split) {
      mj_step(m, d);
      continue;
    }
    if (s > 0) mj_step1(m, d);
    mj_step2(m, d);
  }
  if (!StateOk(m, d, max_speed)) {
    d->time = saved[0];
    std::copy(saved.begin() + 1, saved.begin() + 1 + nq, d->qpos);
    std::copy(saved.begin() + 1 + nq, saved.begin() + 1 + nq + nv, d->qvel);
    std::copy(saved.begin() + 1 + nq + nv, saved.end(), d->qacc_warmstart);
    mj_forward(m, d);  // every stage of the restored state, mj_step1's included
    ok = false;
  }
  return true;
}

template <typename T>
void WriteState(const mjModel* m, const mjData* d, T* qpos, T* qvel) {
  for (int i = 0; i < m->nq; ++i) qpos[i] = static_cast<T>(d->qpos[i]);
  for (int i = 0; i < m->nv; ++i) qvel[i] = static_cast<T>(d->qvel[i]);
}

template <typename T>
ffi::Error StepAll(ffi::Buffer<ffi::U32> handles, ffi::AnyBuffer ctrl, ffi::AnyBuffer xfrc,
                   ffi::Buffer<ffi::PRED> ok, double max_speed, ffi::Result<ffi::AnyBuffer> qpos,
                   ffi::Result<ffi::AnyBuffer> qvel, ffi::Result<ffi::Buffer<ffi::PRED>> ok_out) {
  const int64_t B = handles.dimensions()[0];
  auto xd = xfrc.dimensions();  // (B, n_sub, nbody, 6)
  if (handles.dimensions().size() != 2 || handles.dimensions()[1] != 4 || xd.size() != 4) {
    return ffi::Error::InvalidArgument("wbc_mujoco_step: handles (B, 4) and xfrc (B, n_sub, nbody, 6) expected");
  }
  const int64_t n_sub = xd[1];
  const uint32_t* h = handles.typed_data();
  std::vector<mjtNum> saved;
  DefaultFloatMode mode;
  const int64_t start = ThreadCpuNs();
  for (int64_t b = 0; b < B; ++b) {
    Env e = EnvAt(h, b);
    if (xd[2] != e.m->nbody || ctrl.element_count() != static_cast<size_t>(B * e.m->nu) ||
        qpos->element_count() != static_cast<size_t>(B * e.m->nq) ||
        qvel->element_count() != static_cast<size_t>(B * e.m->nv)) {
      return ffi::Error::InvalidArgument("wbc_mujoco_step: ctrl, xfrc, qpos or qvel do not match the model's sizes");
    }
    bool env_ok = ok.typed_data()[b];
    StepEnv<T>(e, ctrl.typed_data<T>() + b * e.m->nu, xfrc.typed_data<T>() + b * n_sub * 6 * e.m->nbody, n_sub,
               false, max_speed, env_ok, saved);
    WriteState<T>(e.m, e.d, qpos->typed_data<T>() + b * e.m->nq, qvel->typed_data<T>() + b * e.m->nv);
    ok_out->typed_data()[b] = env_ok;
  }
  physics_ns += ThreadCpuNs() - start;
  physics_ticks += 1;
  return ffi::Error::Success();
}

ffi::Error Step(ffi::Buffer<ffi::U32> handles, ffi::AnyBuffer ctrl, ffi::AnyBuffer xfrc, ffi::Buffer<ffi::PRED> ok,
                double max_speed, ffi::Result<ffi::AnyBuffer> qpos, ffi::Result<ffi::AnyBuffer> qvel,
                ffi::Result<ffi::Buffer<ffi::PRED>> ok_out) {
  switch (ctrl.element_type()) {
    case ffi::DataType::F32:
      return StepAll<float>(handles, ctrl, xfrc, ok, max_speed, qpos, qvel, ok_out);
    case ffi::DataType::F64:
      return StepAll<double>(handles, ctrl, xfrc, ok, max_speed, qpos, qvel, ok_out);
    default:
      return ffi::Error::InvalidArgument("wbc_mujoco_step: float32 or float64 arrays expected");
  }
}

// HostBatch.contacts of one environment: its contact slots padded to C: points (C, 3), the
// world-axes force on geom 2 (C, 3) and geom ids (C, 2); separated contacts and padding have zero
// force, point zero and geoms 0.
template <typename T>
void EnvContacts(const mjModel* m, const mjData* d, int64_t C, T* p, T* f, int32_t* g) {
  std::fill(p, p + C * 3, T(0));
  std::fill(f, f + C * 3, T(0));
  std::fill(g, g + C * 2, 0);
  const int64_t n = std::min<int64_t>(d->ncon, C);
  for (int64_t c = 0; c < n; ++c) {
    const mjContact& con = d->contact[c];
    if (con.dist > 0) continue;
    mjtNum f6[6];
    mj_contactForce(m, d, static_cast<int>(c), f6);
    for (int j = 0; j < 3; ++j) {
      mjtNum w = 0;  // frame^T f: the contact frame's rows are its axes
      for (int i = 0; i < 3; ++i) w += con.frame[3 * i + j] * f6[i];
      f[c * 3 + j] = static_cast<T>(w);
      p[c * 3 + j] = static_cast<T>(con.pos[j]);
    }
    g[c * 2] = con.geom[0];
    g[c * 2 + 1] = con.geom[1];
  }
}

template <typename T>
ffi::Error ContactsAll(ffi::Buffer<ffi::U32> handles, ffi::Result<ffi::AnyBuffer> pos,
                       ffi::Result<ffi::AnyBuffer> force, ffi::Result<ffi::Buffer<ffi::S32>> geom) {
  const int64_t B = handles.dimensions()[0];
  const int64_t C = pos->dimensions()[1];
  DefaultFloatMode mode;
  for (int64_t b = 0; b < B; ++b) {
    Env e = EnvAt(handles.typed_data(), b);
    EnvContacts<T>(e.m, e.d, C, pos->typed_data<T>() + b * C * 3, force->typed_data<T>() + b * C * 3,
                   geom->typed_data() + b * C * 2);
  }
  return ffi::Error::Success();
}

ffi::Error Contacts(ffi::Buffer<ffi::U32> handles, ffi::AnyBuffer after, ffi::Result<ffi::AnyBuffer> pos,
                    ffi::Result<ffi::AnyBuffer> force, ffi::Result<ffi::Buffer<ffi::S32>> geom) {
  (void)after;  // the step's output: orders this call after the tick's physics
  switch (pos->element_type()) {
    case ffi::DataType::F32:
      return ContactsAll<float>(handles, pos, force, geom);
    case ffi::DataType::F64:
      return ContactsAll<double>(handles, pos, force, geom);
    default:
      return ffi::Error::InvalidArgument("wbc_mujoco_contacts: float32 or float64 arrays expected");
  }
}

// What the controller's dynamics terms need of one environment's data after mj_step1, in
// MuJoCo's order (wbc_jax.robot.dynamics.terms_from_engine converts them): the mass matrix, bias
// and passive forces, body poses, the CoM, each frame's Jacobian [point; angular] (6, nv) and its
// Jdot qvel, and the centroidal momentum matrix [sum m Jp; sum I_W Jr + m S(xipos - c) Jp] (6, nv)
// with the CoM rows' Jdot qvel times the mass (sum m Jpdot qvel).
template <typename T>
struct TermsOut {
  T *M, *bias, *passive, *xpos, *xmat, *com, *J, *jdot_nu, *A_G, *com_jdot_nu;
};

template <typename T>
void EnvTerms(const mjModel* m, const mjData* d, int base, ffi::Span<const int64_t> bodies,
              ffi::Span<const double> points, TermsOut<T> o, std::vector<mjtNum>& work) {
  const int nv = m->nv, nbody = m->nbody;
  work.resize(nv * nv + 18 * nv);
  mjtNum* full = work.data();
  mjtNum* jac = full + nv * nv;  // jacp (3, nv) then jacr (3, nv)
  mjtNum* dot = jac + 6 * nv;    // their time derivatives
  mjtNum* acc = dot + 6 * nv;    // A_G (6, nv)
  mj_fullM(m, d, full);
  std::transform(full, full + nv * nv, o.M, [](mjtNum x) { return static_cast<T>(x); });
  for (int i = 0; i < nv; ++i) {
    o.bias[i] = static_cast<T>(d->qfrc_bias[i]);
    o.passive[i] = static_cast<T>(d->qfrc_passive[i]);
  }
  for (int i = 0; i < 3 * nbody; ++i) o.xpos[i] = static_cast<T>(d->xpos[i]);
  for (int i = 0; i < 9 * nbody; ++i) o.xmat[i] = static_cast<T>(d->xmat[i]);
  const mjtNum* c = d->subtree_com + 3 * base;
  for (int i = 0; i < 3; ++i) o.com[i] = static_cast<T>(c[i]);
  auto times_qvel = [&](const mjtNum* row) {
    mjtNum sum = 0;
    for (int j = 0; j < nv; ++j) sum += row[j] * d->qvel[j];
    return sum;
  };
  for (size_t f = 0; f < bodies.size(); ++f) {
    const int b = static_cast<int>(bodies[f]);
    const mjtNum* R = d->xmat + 9 * b;
    mjtNum point[3];
    for (int i = 0; i < 3; ++i) {
      point[i] = d->xpos[3 * b + i];
      for (int j = 0; j < 3; ++j) point[i] += R[3 * i + j] * points[3 * f + j];
    }
    mj_jac(m, d, jac, jac + 3 * nv, point, b);
    mj_jacDot(m, d, dot, dot + 3 * nv, point, b);
    std::transform(jac, jac + 6 * nv, o.J + f * 6 * nv, [](mjtNum x) { return static_cast<T>(x); });
    for (int r = 0; r < 6; ++r) o.jdot_nu[6 * f + r] = static_cast<T>(times_qvel(dot + r * nv));
  }
  std::fill(acc, acc + 6 * nv, mjtNum(0));
  mjtNum com_acc[3] = {0, 0, 0};
  for (int b = 1; b < nbody; ++b) {
    const mjtNum mass = m->body_mass[b];
    const mjtNum* xi = d->xipos + 3 * b;
    const mjtNum* R = d->ximat + 9 * b;
    const mjtNum* inertia = m->body_inertia + 3 * b;
    mj_jac(m, d, jac, jac + 3 * nv, xi, b);
    mj_jacDot(m, d, dot, nullptr, xi, b);
    mjtNum I_W[9], r[3];  // R diag(inertia) R^T; the body's CoM from the robot's
    for (int i = 0; i < 3; ++i) {
      r[i] = xi[i] - c[i];
      for (int j = 0; j < 3; ++j) {
        I_W[3 * i + j] = 0;
        for (int k = 0; k < 3; ++k) I_W[3 * i + j] += R[3 * i + k] * inertia[k] * R[3 * j + k];
      }
    }
    const mjtNum* jp = jac;
    const mjtNum* jr = jac + 3 * nv;
    for (int v = 0; v < nv; ++v) {
      const mjtNum p0 = jp[v], p1 = jp[nv + v], p2 = jp[2 * nv + v];
      const mjtNum w0 = jr[v], w1 = jr[nv + v], w2 = jr[2 * nv + v];
      acc[v] += mass * p0;
      acc[nv + v] += mass * p1;
      acc[2 * nv + v] += mass * p2;
      // I_W jr + m r x jp
      acc[3 * nv + v] += I_W[0] * w0 + I_W[1] * w1 + I_W[2] * w2 + mass * (r[1] * p2 - r[2] * p1);
      acc[4 * nv + v] += I_W[3] * w0 + I_W[4] * w1 + I_W[5] * w2 + mass * (r[2] * p0 - r[0] * p2);
      acc[5 * nv + v] += I_W[6] * w0 + I_W[7] * w1 + I_W[8] * w2 + mass * (r[0] * p1 - r[1] * p0);
    }
    for (int i = 0; i < 3; ++i) com_acc[i] += mass * times_qvel(dot + i * nv);
  }
  std::transform(acc, acc + 6 * nv, o.A_G, [](mjtNum x) { return static_cast<T>(x); });
  for (int i = 0; i < 3; ++i) o.com_jdot_nu[i] = static_cast<T>(com_acc[i]);
}

// CPU time of the calling threads extracting the dynamics terms (the controller's share of
// WbcMujocoStepTerms; its mj_step1 and mj_step2 count as physics).
std::atomic<int64_t> terms_ns{0};

// The C MuJoCo engine's tick with the controller's dynamics terms from C MuJoCo: the data hold
// mj_step1 of the current state between calls. start: the loop's first call, which steps nothing
// (it runs mj_step1 at the initial state). Otherwise each environment steps as StepEnv (split),
// then runs mj_step1 at its new state (not when it diverged: mj_forward did, at the restored one).
// The contact slots are read before that mj_step1, so they describe what mj_step's would; an
// environment that did not step passes on the slots it was given (its data moved on to mj_step1).
// Then every environment's terms, at the state returned.
template <typename T>
ffi::Error StepTermsAll(ffi::Buffer<ffi::U32> handles, ffi::AnyBuffer ctrl, ffi::AnyBuffer xfrc,
                        ffi::Buffer<ffi::PRED> ok, ffi::AnyBuffer pos_in, ffi::AnyBuffer force_in,
                        ffi::Buffer<ffi::S32> geom_in, double max_speed, bool start, int64_t base,
                        ffi::Span<const int64_t> bodies, ffi::Span<const double> points, ffi::RemainingRets rets) {
  const int64_t B = handles.dimensions()[0];
  auto xd = xfrc.dimensions();  // (B, n_sub, nbody, 6)
  auto cd = pos_in.dimensions();  // (B, C, 3)
  if (handles.dimensions().size() != 2 || handles.dimensions()[1] != 4 || xd.size() != 4 || cd.size() != 3 ||
      rets.size() != 16) {
    return ffi::Error::InvalidArgument(
        "wbc_mujoco_step_terms: handles (B, 4), xfrc (B, n_sub, nbody, 6), contact slots (B, C, 3) and 16 results "
        "expected");
  }
  if (points.size() != 3 * bodies.size()) {
    return ffi::Error::InvalidArgument("wbc_mujoco_step_terms: frame_points must hold 3 numbers per frame body");
  }
  const int64_t n_sub = xd[1], C = cd[1], K = static_cast<int64_t>(bodies.size());
  T* out[16];
  for (int i = 0; i < 16; ++i) {
    if (i == 2 || i == 5) continue;  // ok, geom ids
    auto r = rets.get<ffi::AnyBuffer>(i);
    if (r.has_error()) return r.error();
    out[i] = (*r)->typed_data<T>();
  }
  auto ok_out = rets.get<ffi::Buffer<ffi::PRED>>(2);
  auto geom_out = rets.get<ffi::Buffer<ffi::S32>>(5);
  if (ok_out.has_error()) return ok_out.error();
  if (geom_out.has_error()) return geom_out.error();
  const uint32_t* h = handles.typed_data();
  std::vector<mjtNum> saved, work;
  DefaultFloatMode mode;
  for (int64_t b = 0; b < B; ++b) {
    Env e = EnvAt(h, b);
    const mjModel* m = e.m;
    const int nq = m->nq, nv = m->nv, nbody = m->nbody;
    if (xd[2] != nbody || ctrl.element_count() != static_cast<size_t>(B * m->nu) || base < 0 || base >= nbody ||
        rets.get<ffi::AnyBuffer>(6).value()->element_count() != static_cast<size_t>(B * nv * nv) ||
        rets.get<ffi::AnyBuffer>(12).value()->element_count() != static_cast<size_t>(B * K * 6 * nv) ||
        rets.get<ffi::AnyBuffer>(0).value()->element_count() != static_cast<size_t>(B * nq)) {
      return ffi::Error::InvalidArgument("wbc_mujoco_step_terms: the arrays do not match the model's sizes");
    }
    for (int64_t body : bodies) {
      if (body < 0 || body >= nbody) return ffi::Error::InvalidArgument("wbc_mujoco_step_terms: a frame body out of range");
    }
    bool env_ok = ok.typed_data()[b];
    const int64_t t0 = ThreadCpuNs();
    const bool stepped = !start && StepEnv<T>(e, ctrl.typed_data<T>() + b * m->nu,
                                              xfrc.typed_data<T>() + b * n_sub * 6 * nbody, n_sub, true, max_speed,
                                              env_ok, saved);
    const int64_t t1 = ThreadCpuNs();
    T* pos = out[3] + b * C * 3;
    T* force = out[4] + b * C * 3;
    int32_t* geom = (*geom_out)->typed_data() + b * C * 2;
    if (start || stepped) {
      EnvContacts<T>(m, e.d, C, pos, force, geom);
    } else {
      std::copy(pos_in.typed_data<T>() + b * C * 3, pos_in.typed_data<T>() + (b + 1) * C * 3, pos);
      std::copy(force_in.typed_data<T>() + b * C * 3, force_in.typed_data<T>() + (b + 1) * C * 3, force);
      std::copy(geom_in.typed_data() + b * C * 2, geom_in.typed_data() + (b + 1) * C * 2, geom);
    }
    const int64_t t2 = ThreadCpuNs();
    if (start ? StateOk(m, e.d, max_speed) : stepped && env_ok) mj_step1(m, e.d);
    const int64_t t3 = ThreadCpuNs();
    WriteState<T>(m, e.d, out[0] + b * nq, out[1] + b * nv);
    (*ok_out)->typed_data()[b] = env_ok;
    TermsOut<T> terms{out[6] + b * nv * nv,    out[7] + b * nv,         out[8] + b * nv,
                      out[9] + b * nbody * 3,  out[10] + b * nbody * 9, out[11] + b * 3,
                      out[12] + b * K * 6 * nv, out[13] + b * K * 6,    out[14] + b * 6 * nv,
                      out[15] + b * 3};
    EnvTerms<T>(m, e.d, static_cast<int>(base), bodies, points, terms, work);
    physics_ns += (t1 - t0) + (t3 - t2);
    terms_ns += ThreadCpuNs() - t3;
  }
  if (!start) physics_ticks += 1;
  return ffi::Error::Success();
}

ffi::Error StepTerms(ffi::Buffer<ffi::U32> handles, ffi::AnyBuffer ctrl, ffi::AnyBuffer xfrc,
                     ffi::Buffer<ffi::PRED> ok, ffi::AnyBuffer pos_in, ffi::AnyBuffer force_in,
                     ffi::Buffer<ffi::S32> geom_in, double max_speed, bool start, int64_t base_body,
                     ffi::Span<const int64_t> frame_bodies, ffi::Span<const double> frame_points,
                     ffi::RemainingRets rets) {
  switch (ctrl.element_type()) {
    case ffi::DataType::F32:
      return StepTermsAll<float>(handles, ctrl, xfrc, ok, pos_in, force_in, geom_in, max_speed, start, base_body,
                                 frame_bodies, frame_points, rets);
    case ffi::DataType::F64:
      return StepTermsAll<double>(handles, ctrl, xfrc, ok, pos_in, force_in, geom_in, max_speed, start, base_body,
                                  frame_bodies, frame_points, rets);
    default:
      return ffi::Error::InvalidArgument("wbc_mujoco_step_terms: float32 or float64 arrays expected");
  }
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(WbcMujocoStep, Step,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::PRED>>()
                                  .Attr<double>("max_speed")
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::Buffer<ffi::PRED>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(WbcMujocoStepTerms, StepTerms,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::PRED>>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Attr<double>("max_speed")
                                  .Attr<bool>("start")
                                  .Attr<int64_t>("base_body")
                                  .Attr<ffi::Span<const int64_t>>("frame_bodies")
                                  .Attr<ffi::Span<const double>>("frame_points")
                                  .RemainingRets());

XLA_FFI_DEFINE_HANDLER_SYMBOL(WbcMujocoContacts, Contacts,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::U32>>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::Buffer<ffi::S32>>());

extern "C" {
// The physics counters: CPU nanoseconds and ticks since the last reset (wbc_jax.sim.native.physics_cpu).
int64_t WbcMujocoPhysicsNs() { return physics_ns.load(); }
int64_t WbcMujocoPhysicsTicks() { return physics_ticks.load(); }
// CPU nanoseconds extracting the dynamics terms (WbcMujocoStepTerms): the controller's, not the physics'.
int64_t WbcMujocoTermsNs() { return terms_ns.load(); }
void WbcMujocoResetCounters() {
  physics_ns = 0;
  physics_ticks = 0;
  terms_ns = 0;
}
}
