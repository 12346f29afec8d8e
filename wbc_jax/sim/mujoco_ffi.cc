// C MuJoCo called from inside an XLA program through XLA's FFI (jax.ffi): the physics of one
// control tick of the closed loop and the contact slots after it, for wbc_jax.sim.mujoco_scan.
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
template <typename T>
void StepEnv(Env e, const T* ctrl, const T* xfrc, int64_t n_sub, bool ok, double max_speed, T* qpos, T* qvel,
             bool* ok_out, std::vector<mjtNum>& saved) {
  const mjModel* m = e.m;
  mjData* d = e.d;
  if (ok) {
    bool ctrl_ok = true;
    for (int i = 0; i < m->nu; ++i) ctrl_ok = ctrl_ok && std::isfinite(static_cast<double>(ctrl[i]));
    ok = ctrl_ok && StateOk(m, d, max_speed);
  }
  if (ok) {
    const int nq = m->nq, nv = m->nv, nb6 = 6 * m->nbody;
    saved.resize(1 + nq + 2 * nv);
    saved[0] = d->time;
    std::copy(d->qpos, d->qpos + nq, saved.begin() + 1);
    std::copy(d->qvel, d->qvel + nv, saved.begin() + 1 + nq);
    std::copy(d->qacc_warmstart, d->qacc_warmstart + nv, saved.begin() + 1 + nq + nv);
    for (int i = 0; i < m->nu; ++i) d->ctrl[i] = static_cast<mjtNum>(ctrl[i]);
    for (int64_t s = 0; s < n_sub; ++s) {
      for (int j = 0; j < nb6; ++j) d->xfrc_applied[j] = static_cast<mjtNum>(xfrc[s * nb6 + j]);
      mj_step(m, d);
    }
    if (!StateOk(m, d, max_speed)) {
      d->time = saved[0];
      std::copy(saved.begin() + 1, saved.begin() + 1 + nq, d->qpos);
      std::copy(saved.begin() + 1 + nq, saved.begin() + 1 + nq + nv, d->qvel);
      std::copy(saved.begin() + 1 + nq + nv, saved.end(), d->qacc_warmstart);
      mj_forward(m, d);
      ok = false;
    }
  }
  for (int i = 0; i < m->nq; ++i) qpos[i] = static_cast<T>(d->qpos[i]);
  for (int i = 0; i < m->nv; ++i) qvel[i] = static_cast<T>(d->qvel[i]);
  *ok_out = ok;
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
    StepEnv<T>(e, ctrl.typed_data<T>() + b * e.m->nu, xfrc.typed_data<T>() + b * n_sub * 6 * e.m->nbody, n_sub,
               ok.typed_data()[b], max_speed, qpos->typed_data<T>() + b * e.m->nq,
               qvel->typed_data<T>() + b * e.m->nv, ok_out->typed_data() + b, saved);
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

// HostBatch.contacts: the contact slots of each environment padded to C: points (B, C, 3), the
// world-axes force on geom 2 (B, C, 3) and geom ids (B, C, 2); separated contacts and padding
// have zero force, point zero and geoms 0.
template <typename T>
ffi::Error ContactsAll(ffi::Buffer<ffi::U32> handles, ffi::Result<ffi::AnyBuffer> pos,
                       ffi::Result<ffi::AnyBuffer> force, ffi::Result<ffi::Buffer<ffi::S32>> geom) {
  const int64_t B = handles.dimensions()[0];
  const int64_t C = pos->dimensions()[1];
  T* p = pos->typed_data<T>();
  T* f = force->typed_data<T>();
  int32_t* g = geom->typed_data();
  std::fill(p, p + B * C * 3, T(0));
  std::fill(f, f + B * C * 3, T(0));
  std::fill(g, g + B * C * 2, 0);
  DefaultFloatMode mode;
  for (int64_t b = 0; b < B; ++b) {
    Env e = EnvAt(handles.typed_data(), b);
    const int64_t n = std::min<int64_t>(e.d->ncon, C);
    for (int64_t c = 0; c < n; ++c) {
      const mjContact& con = e.d->contact[c];
      if (con.dist > 0) continue;
      mjtNum f6[6];
      mj_contactForce(e.m, e.d, static_cast<int>(c), f6);
      const int64_t at = (b * C + c) * 3;
      for (int j = 0; j < 3; ++j) {
        mjtNum w = 0;  // frame^T f: the contact frame's rows are its axes
        for (int i = 0; i < 3; ++i) w += con.frame[3 * i + j] * f6[i];
        f[at + j] = static_cast<T>(w);
        p[at + j] = static_cast<T>(con.pos[j]);
      }
      g[(b * C + c) * 2] = con.geom[0];
      g[(b * C + c) * 2 + 1] = con.geom[1];
    }
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
void WbcMujocoResetCounters() {
  physics_ns = 0;
  physics_ticks = 0;
}
}
