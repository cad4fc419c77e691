"""Fine-tuning the servo part through the WLS (tried in session 32, not adopted).

The folds fine-tune the physical model's 16 servo parameters on the torque MSE of the known
object's real samples. This fine-tunes them instead on the mass and COM error of the WLS
over 250 sets of 64 of those samples (the attention's loss, every joint weighted alike:
T), from the same simulator-trained starts of a finished run's folds, and judges T on the
held-out file (and, **not held out**, on the fold's own file). Full-batch Adam at 1e-3.

    python experiments/wls_finetune.py --run DIR --lbipe-dir DIR [--steps 300] [--w-com 0.3]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # the least squares in float64, as the CLI's

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from jaxinertia.app.pipeline import adapt_objects, load_real, session_reference  # noqa: E402
from jaxinertia.checkpoints import load_models  # noqa: E402
from jaxinertia.features import featurize  # noqa: E402
from jaxinertia.training import SERVO_PARAMS  # noqa: E402
from jaxinertia.training_setup import draw_sets  # noqa: E402

STARTS = ("models_physical", "models_physical_current", "models_physical_current_sessions")
SAMPLES = (64, 250, 1000)


def wls(A, y, sets):
    """(K, B, 4) unweighted least squares of ``y`` (K, S, N) on ``A`` (S, N, 4) per set."""
    As, ys = A[sets], y[:, sets]
    G = jnp.einsum("bmni,bmnj->bij", As, As)
    return jnp.einsum("bij,kbj->kbi", jnp.linalg.inv(G), jnp.einsum("bmni,kbmn->kbi", As, ys))


def metrics(x, obj, l_max: float) -> tuple[float, float, float]:
    """Mass NMAE, COM NMAE and mass bias [%]."""
    xt = np.asarray(obj.x).reshape(-1, 4)[0]
    x = np.asarray(x)
    em = x[..., 0] - xt[0]
    ec = np.linalg.norm(x[..., 1:] / x[..., :1] - xt[1:] / xt[0], axis=-1)
    return (100 * np.mean(np.abs(em)) / xt[0], 100 * np.mean(ec) / l_max,
            100 * np.mean(em) / xt[0])


class Start:
    """A fold's simulator-trained physical models with their servo part as variables."""

    def __init__(self, path: Path, real):
        folder = load_models(path)
        self.pair, fc = folder.pair, folder.features
        self.objects, _ = adapt_objects(real.objects, session_reference(folder.config, 0.0))
        self.features = [featurize(fc, jnp.asarray(o.q), jnp.asarray(o.q_d),
                                   jnp.asarray(o.direction), jnp.asarray(o.current_tau)
                                   ).astype(jnp.float32) for o in self.objects]
        self.scale = jnp.asarray(self.pair.tau_scale, jnp.float32)
        params = self.pair.torque_vars["params"]
        self.servo = {k: params[k] for k in SERVO_PARAMS}
        self.rest = {k: v for k, v in params.items() if k not in SERVO_PARAMS}

    def torques(self, servo, o: int, rows=None):
        f = self.features[o] if rows is None else self.features[o][rows]
        model = self.pair.torque_model
        tau = jax.vmap(lambda v: model.apply({"params": v}, f))({**self.rest, **servo})
        return (tau * self.scale).astype(jnp.float64)

    def judge(self, servo, o: int, real) -> tuple[float, float, float]:
        obj = self.objects[o]
        x = wls(jnp.asarray(obj.A), self.torques(servo, o) - jnp.asarray(obj.tau_g)[None],
                jnp.asarray(real.sets[o]))
        return metrics(x, obj, real.l_max[o])

    def finetune(self, fit: int, n: int, steps: int, w_com: float):
        """The servo part fitted to the mass and COM of sets of ``n`` samples of ``fit``."""
        obj = self.objects[fit]
        rng = np.random.default_rng(0)
        sub = (np.sort(rng.choice(obj.n_samples, n, replace=False)) if n < obj.n_samples
               else np.arange(obj.n_samples))
        sets = jnp.asarray(np.searchsorted(sub, sub[draw_sets(np.zeros(n, int), 250, 64, 0)]))
        A, tg = jnp.asarray(obj.A)[sub], jnp.asarray(obj.tau_g)[sub]
        xt = jnp.asarray(np.asarray(obj.x).reshape(-1, 4)[0])

        def loss(servo):
            x = wls(A, self.torques(servo, fit, sub) - tg[None], sets)
            e_p = jnp.linalg.norm((x[..., 1:] - xt[1:]) / xt[0], axis=-1)
            return jnp.mean((x[..., 0] - xt[0]) ** 2) + w_com * jnp.mean(e_p ** 2)

        opt = optax.adam(1e-3)

        @jax.jit
        def step(servo, state):
            grads = jax.grad(loss)(servo)
            updates, state = opt.update(grads, state, servo)
            return optax.apply_updates(servo, updates), state

        servo, state = self.servo, opt.init(self.servo)
        for _ in range(steps):
            servo, state = step(servo, state)
        return servo


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, type=Path, help="a reproduce --full output folder")
    p.add_argument("--lbipe-dir", required=True)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--w-com", type=float, default=0.3)
    args = p.parse_args()
    real = load_real(args.lbipe_dir)
    names = [o.name for o in real.objects]
    print("T mass NMAE (bias) / COM NMAE [%]: held out | the fold's own file (not held out)")
    for fit_name in names:
        fit = names.index(fit_name)
        held = 1 - fit
        for start in STARTS:
            s = Start(args.run / "folds" / f"fit_{fit_name}" / start, real)
            tuned = [("simulator only", s.servo)] + [
                (f"WLS-tuned on {n}", s.finetune(fit, n, args.steps, args.w_com))
                for n in SAMPLES]
            for tag, servo in tuned:
                h, own = s.judge(servo, held, real), s.judge(servo, fit, real)
                print(f"fit {fit_name} {start:34s} {tag:16s} {names[held]}: {h[0]:6.2f} "
                      f"({h[2]:+6.2f}) / {h[1]:6.2f} | {fit_name}: {own[0]:6.2f} "
                      f"({own[2]:+6.2f}) / {own[1]:6.2f}", flush=True)


if __name__ == "__main__":
    main()
