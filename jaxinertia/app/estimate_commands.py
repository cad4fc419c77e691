"""Commands for an unknown object: ``estimate`` (mass and COM with standard errors and
intervals, refusing what the poses cannot determine) and ``plan-poses`` (the most
informative poses to visit)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from jaxinertia.app import defaults
from jaxinertia.app.arm_options import add_arm_option, arm_name, arm_of
from jaxinertia.app.options import (
    add_session_strength,
    check_memory,
    check_outputs,
    enable_x64,
    nonnegative_float,
    positive_float,
    positive_int,
    seed_int,
    servo_state_line,
    session_line,
    write_json_option,
)
from jaxinertia.errors import UsageError

__all__ = ["register"]

#: What one configuration of the planning grid takes while the plan is chosen (its 2^N
#: direction copies, collision test, regressor and information matrix) [bytes], generous.
PLAN_BYTES_PER_CONFIGURATION = 4096


def _pm(value: float, se: float) -> str:
    return f"{value:.1f} +- {se:.1f}"


def reference_session_line(name: str, state: dict) -> str:
    """Whether the reference looks recorded in this file's session (its current gain per
    joint, and the supply and temperature where both files recorded them)."""
    gains = " / ".join("-" if g is None else f"{g:.3f} +- {se:.3f}"
                       for g, se in zip(state["current_gain_ratio"] or [],
                                        state["current_gain_ratio_se"] or []))
    facts = f"current gain x {gains}" if gains else "no current gain to compare"
    if state["same_session"] is None:
        verdict = "cannot tell whether it is this file's session"
    elif state["same_session"]:
        verdict = ("consistent with one session (the current gain tells another session, "
                   "3-6 % apart as the two real files, from about 1000 samples each; the "
                   "supply and temperature, where both files recorded them, at once)")
    else:
        verdict = (f"ANOTHER SESSION, it seems (joint(s) {state['other_session_joints']}): a "
                   "reference from another session moves the answer, it does not correct it "
                   "(docs/results.md, 'A reference in the same session')")
    return f"{name}: this file against the reference: {facts}: {verdict}"


def reference_line(ref: dict) -> str:
    """What ``estimate --reference`` fitted: the models' torques against the known ones."""
    c = ref["correction"]
    gains = " / ".join(f"{g:.3f} +- {se:.3f}" for g, se in zip(c["gain"], c["gain_se"]))
    offsets = " / ".join(f"{b * 1e3:+.1f}" for b in c["offset_Nm"])
    k = len(ref["members"])
    more = ("" if not k else "; the further member fits its own" if k == 1 else
            f"; each of the {k} further members fits its own")
    more += "; so do the COM's models" if ref.get("com_models") else ""
    empty = ("; its empty-gripper samples weaken it (a known weight alone did better on "
             "the simulator)" if ref.get("empty_gripper") else "")
    return (f"reference {ref['file']} ({', '.join(ref['objects'])}, {ref['n_samples']} "
            f"samples of known torque): the networks' torques read x {gains}, "
            f"{offsets} N mm (joints 1-{len(c['gain'])}; fitted on it{more}); "
            f"it must be recorded in this file's session{empty}")


def cmd_estimate(args) -> int:
    check_outputs(args, "--json")
    enable_x64()
    # The work's modules (JAX): imported when the command runs, not for --help.
    import numpy as np

    from jaxinertia.app.estimate import estimate  # (as above)

    res = estimate(args.models, args.samples, set_size=args.set_size, max_mass=args.max_mass,
                   max_com=args.max_com, max_com_se=args.max_com_se,
                   session_strength=args.session_strength, arm=arm_name(args),
                   reference=args.reference)
    floor = res["torque_error_floor"]
    from jaxinertia.app.provenance import not_held_out_line  # (as above)

    seen = {p: (v["folders"], v["of"]) for p, v in res["fitted_on_this_file"].items()}
    if ref := res.get("reference"):
        print(reference_line(ref))
    for name, o in res["objects"].items():
        ident = o["identifiability"]
        print(session_line(name, res["session_strength"], o["session_ratio"]))
        if line := servo_state_line(name, o["servo_state"]):
            print(line)
        if "reference_session" in o:
            print(reference_session_line(name, o["reference_session"]))
        if line := not_held_out_line(name, seen):
            print(line)
        if res.get("uniform_attention"):
            print(f"{name}: these models weight every joint alike (their attention off, as "
                  "the held-out folds chose): T-A answers as T")
        if res.get("ensemble_members"):
            w = res.get("ensemble_weights")
            other = [f"{Path(m).name} {x:.3g}" for m, x in zip(res["ensemble_members"], w[1:] if w
                                                      else ()) if x != w[0]]
            shares = ("" if w is None else f"; shares: {w[0]:.3g} each, but "
                      + ", ".join(other) if other else "")
            print(f"{name}: T and T-A the mean of these models and "
                  f"{len(res['ensemble_members'])} more inside them (each read in its own "
                  f"session{shares}); the baselines from the models above")
        if res.get("com_models"):
            ratio = ", ".join(f"{r:.3f}" for r in o["com_session_ratio"])
            print(f"{name}: the COM of T and T-A from {res['com_models']} (session strength "
                  f"{res['com_session_strength']:g}, x ({ratio}) per joint); the mass and the "
                  "baselines from the models above")
        pc = np.asarray(ident["predicted_com_se_m"]) * 1e3
        print(f"{name}: {o['n_samples']} samples (the spread over {o['set_size']}-sample sets); "
              f"poses: condition {ident['condition']:.1f}, "
              f"predicted standard error mass {ident['predicted_mass_se_kg'] * 1e3:.1f} g, "
              f"COM {pc[0]:.1f} / {pc[1]:.1f} / {pc[2]:.1f} mm "
              f"(torque error: {ident['torque_error_source']})")
        if args.max_com_se is None and np.max(pc) > 50.0:
            print(f"  the poses determine the COM poorly (+-{np.max(pc):.0f} mm predicted); "
                  "--max-com-se refuses such sets")
        print(f"{'method':<7} {'mass [g]':>16} {'COM x [mm]':>16} {'COM y [mm]':>16} "
              f"{'COM z [mm]':>16}   (COM in the tag frame; value +- standard error, then "
              "the 95 % interval)")
        for m, r in o["methods"].items():
            if not r["ok"]:
                print(f"{m:<7} failed: {r['reason']}")
                continue
            c, cs = np.asarray(r["com_tag_m"]) * 1e3, np.asarray(r["com_se_m"]) * 1e3
            print(f"{m:<7} {_pm(r['mass_kg'] * 1e3, r['mass_se_kg'] * 1e3):>16} "
                  + " ".join(f"{_pm(c[i], cs[i]):>16}" for i in range(3)))
            iv = r["interval_95"]
            lo_hi = [np.asarray(iv["mass_kg"]) * 1e3] + list(np.asarray(iv["com_tag_m"]) * 1e3)
            print(f"{'  95 %':<7} " + " ".join(f"{f'[{lo:.1f}, {hi:.1f}]':>16}"
                                            for lo, hi in lo_hi))
        for m, why in o.get("unavailable", {}).items():
            print(f"{m:<7} {why}")
        lead = next((m for m in ("T-A", "T") if o["methods"].get(m, {}).get("ok")), None)
        if lead is not None:
            sens = o["methods"][lead]["servo_state_sensitivity"]
            mass = " / ".join(f"{v * 1e3:+.1f}" for v in sens["mass_kg"])
            com = " / ".join(f"{v * 1e3:.1f}" for v in sens["com_m"])
            print(f"servo state (a bias the intervals do not hold): "
                  f"{sens['torque_fraction'] * 100:g} % of one joint's torque moves {lead}'s "
                  f"mass by {mass} g, its COM by {com} mm (joints 1-{len(sens['mass_kg'])}): "
                  "a servo in another state than the models learnt (supply, temperature)")
    print(f"torque error floor: {floor['source']}" + (
        "" if floor["Nm"] is None else
        " (" + ", ".join(f"{v * 1e3:.0f}" for v in floor["Nm"]) + " N mm per joint)"))
    return write_json_option(args, res)


def _grid_size(workspace, margin_deg: float, step_deg: float) -> float:
    """Configurations of the planning grid over ``workspace`` less ``margin_deg`` (as
    ``plans.planning_plan`` lays it out), before building it."""
    return math.prod(max(0.0, (hi - lo - 2 * margin_deg)) // step_deg + 1 for lo, hi in workspace)


def cmd_plan_poses(args) -> int:
    check_outputs(args, "--out")
    if args.robot is not None and args.workspace is None:
        raise UsageError("--robot needs --workspace LO:HI,... (degrees, one per joint)")
    enable_x64()
    # The work's modules (JAX): imported when the command runs, not for --help.
    import numpy as np

    from jaxinertia.design import arm_plan_kwargs, plan_poses, save_plan  # (as above)
    from jaxinertia.robot import load_robot  # (as above)

    arm = arm_of(args)
    if args.robot is not None:
        robot = load_robot(args.robot)
        kw = dict(robot=robot, step_deg=arm.planning_step_deg, workspace=args.workspace,
                  clearance=arm.mount_clearance_m, tag=(np.eye(3), np.zeros(3)))
    else:  # the arm's record: its robot, planning grid, workspace, clearance, tag mount
        kw = arm_plan_kwargs(arm)
        robot = kw["robot"]
    kw.update({k: v for k, v in (("step_deg", args.step_deg), ("clearance", args.clearance),
                                 ("workspace", args.workspace)) if v is not None})
    workspace = tuple(kw["workspace"])
    n_grid = _grid_size(workspace, args.margin_deg, kw["step_deg"])
    check_memory(n_grid * PLAN_BYTES_PER_CONFIGURATION,
                 f"--step-deg {kw['step_deg']:g} (a planning grid of {n_grid:.3g} "
                 "configurations)")
    if args.joint_weights is not None and len(args.joint_weights) != robot.n_joints:
        raise UsageError(f"--joint-weights: {len(args.joint_weights)} values for "
                         f"{robot.n_joints} joints")
    plan = plan_poses(args.n, **kw, margin_deg=args.margin_deg,
                      joint_weights=args.joint_weights, seed=args.seed)
    if not np.isfinite(plan.logdet):
        raise UsageError(f"--n {args.n}: the best {args.n} poses of the grid do not determine "
                         "mass and COM (singular information matrix): ask for more poses")
    gain = plan.logdet - np.median(plan.random_logdet)
    print(f"{args.n} poses chosen from {plan.n_candidates} collision-free grid configurations "
          f"({kw['step_deg']:g} deg; greedy + {plan.exchanges} exchange(s))")
    print(f"log det information {plan.logdet:.2f}; random {args.n}-pose subsets of the grid: "
          f"median {np.median(plan.random_logdet):.2f}, best of {len(plan.random_logdet)} "
          f"{np.max(plan.random_logdet):.2f} (the plan's confidence ellipsoid of x is "
          f"{np.exp(gain / 2):.1f}x smaller in volume than the median random one's)")
    print("pose " + " ".join(f"{f'q{j + 1} [deg]':>9}" for j in range(robot.n_joints))
          + "  direction")
    for i, (q, d) in enumerate(zip(plan.q_d, plan.direction)):
        print(f"{i:>4} " + " ".join(f"{v:>9.1f}" for v in np.degrees(q)) + "  "
              + " ".join("+" if v > 0 else "-" for v in d))
    save_plan(args.out, plan, robot=robot.name,
              extra={"arm": None if args.robot is not None else arm.name,
                     "grid_step_deg": kw["step_deg"], "margin_deg": args.margin_deg,
                     "workspace_deg": [list(w) for w in workspace],
                     "joint_weights": args.joint_weights})
    print(f"wrote {args.out}")
    return 0


def _poses(text: str) -> int:
    """``--n`` of plan-poses: one pose's gravity wrench spans only 3 of the 4 parameters
    (no moment about the vertical), so a plan needs at least 2."""
    n = positive_int(text)
    if n < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2 (one pose cannot determine mass "
                                         f"and COM), got {text!r}")
    return n


def _ranges_deg(text: str) -> tuple[tuple[float, float], ...]:
    """``LO:HI,LO:HI,...`` [deg], one range per joint (one argument: a leading minus sign
    would read as an option)."""
    out = []
    for part in text.split(","):
        lo, sep, hi = part.partition(":")
        try:
            lo_f, hi_f = float(lo), float(hi)
        except ValueError:
            lo_f = hi_f = float("nan")
        if not sep or not math.isfinite(lo_f) or not math.isfinite(hi_f) or not lo_f < hi_f:
            raise argparse.ArgumentTypeError(
                f"must be LO:HI,LO:HI,... degrees with LO < HI per joint, got {text!r}")
        out.append((lo_f, hi_f))
    return tuple(out)


def register(sub) -> None:
    """Adds this module's subcommands to the ``jaxinertia`` argparse subparsers."""
    m = sub.add_parser("estimate", help="mass and COM of an unknown object from a sample file")
    m.add_argument("--models", required=True, type=Path)
    m.add_argument("--samples", required=True, type=Path)
    add_arm_option(m, default=None, what="the arm the samples record; models of another "
                   "arm are refused")
    m.add_argument("--set-size", type=positive_int, default=None,
                   help="samples per set for the spread over sample sets (default 64, or half "
                   "an object's samples where it has fewer than 128); given, a file needs at "
                   "least this many samples per object")
    m.add_argument("--max-mass", type=positive_float, default=5.0,
                   help="an estimate above this mass [kg] is reported as failed (default 5)")
    m.add_argument("--max-com", type=positive_float, default=0.5,
                   help="an estimate whose COM is farther than this from the tag [m] is "
                   "reported as failed (default 0.5)")
    m.add_argument("--max-com-se", type=positive_float, default=None, metavar="METRES",
                   help="refuse an object whose COM the poses alone determine worse than this "
                   "(predicted standard error [m] at the estimated mass; default: no limit, "
                   "a singular set of poses is always refused)")
    add_session_strength(m)
    m.add_argument("--reference", type=Path, default=None, metavar="FILE",
                   help="a sample file of a known load (a known weight, its truth recorded) "
                   "collected in the same session as --samples, just before or after it: "
                   "each joint's torque gain and offset fitted on it correct the networks' "
                   "torques (the servos' state of the day; docs/results.md, 'A reference in "
                   "the same session')")
    m.add_argument("--json", type=Path,
                   help="write every answer here, with standard errors, 68/95 %% intervals and "
                   "the covariance of x = [m, m p]")
    m.add_argument("--overwrite", action="store_true", help="replace an existing --json")
    m.set_defaults(func=cmd_estimate)

    pp = sub.add_parser(
        "plan-poses", help="choose the N most informative poses (D-optimal) for an estimate",
        description="Chooses N configurations of the collision-free planning grid that "
        "maximise log det of the load regressor's information sum_s A_s^T W A_s (greedy, "
        "then exchanges), and approach directions that cancel a friction-like error; "
        "writes a JSON plan (q_d [rad], direction +1/-1 per pose).")
    pp.add_argument("--n", type=_poses, default=16,
                    help="poses (default 16; at least 2: one pose cannot determine mass and "
                    "COM)")
    pp.add_argument("--out", required=True, type=Path, help="plan file to write (JSON)")
    add_arm_option(pp)
    pp.add_argument("--step-deg", type=positive_float,
                    help="grid step over the workspace (default: the arm's, 10 for the "
                    "OpenMANIPULATOR-X)")
    pp.add_argument("--margin-deg", type=nonnegative_float, default=defaults.MARGIN_DEG,
                    help="keep the poses this far inside every joint range: the torque models "
                    "are least accurate at the limits (default %(default)s)")
    pp.add_argument("--clearance", type=positive_float,
                    help="minimum end-effector height over the mounting surface [m] "
                    "(default: the arm's, 0.1 for the OpenMANIPULATOR-X)")
    pp.add_argument("--joint-weights", type=positive_float, nargs="+",
                    help="W's weight per joint (e.g. 1/sigma_j^2 of the torque error; default "
                    "equal)")
    pp.add_argument("--robot", type=Path, help="an MJCF (.xml) or URDF of another serial arm "
                    "without an arm record (default: the --arm's description)")
    pp.add_argument("--workspace", type=_ranges_deg, metavar="LO:HI,...",
                    help="joint ranges in degrees, one per joint, e.g. "
                    "--workspace=-30:30,-50:-10,10:50,-20:20 (default: the arm's)")
    pp.add_argument("--seed", type=seed_int, default=0,
                    help="seed of the random reference plans")
    pp.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    pp.set_defaults(func=cmd_plan_poses)
