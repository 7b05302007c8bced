"""Issue 30's first target on a whole file: every stored sample satisfies the equations of motion.

    python bench/vehicles_eom.py data/fcm4.h5 [--split test]

Newton's law for each body and Euler's for each angle, written from the forces of the springs and
dampers (not from physics/vehicle_model.py's matrices), at every stored sample of every recording:
prints per degree of freedom the largest |residual| / (that degree of freedom's RMS acceleration in its
recording), over the file, against the target 1e-6. tests/test_vehicle_model.py checks the same on small files.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from hybridqcm.data.hdf5 import read_split
from hybridqcm.physics.vehicle_geometry import VehicleLayout


def force_balance(layout: VehicleLayout, physical, accel, vel, disp, road, road_vel=None) -> np.ndarray:
    """accel - (generalised force / mass) [M, T, n_dof]: each element's force on its two bodies."""
    d = {name: i for i, name in enumerate(layout.dofs)}
    P = {n: physical[:, j][:, None] for j, n in enumerate(layout.param_names)}
    z2, th, v2, om = disp[..., d["z2"]], disp[..., d["pitch"]], vel[..., d["z2"]], vel[..., d["pitch"]]
    ph = disp[..., d["roll"]] if layout.full else np.zeros_like(z2)
    w_ph = vel[..., d["roll"]] if layout.full else np.zeros_like(z2)
    force = {name: np.zeros_like(z2) for name in layout.dofs}

    def on_body(f, x, y):
        force["z2"] += f
        force["pitch"] += f * x
        if layout.full:
            force["roll"] += f * y

    for s in layout.seat_names:
        key, x = f"z3{layout.suffix(s)}", P[layout.seat_param("x_s", s)]
        y = P[layout.seat_param("y_s", s)] if layout.full else 0.0
        f = -P[layout.seat_param("k3", s)] * (disp[..., d[key]] - (z2 + x * th + y * ph))
        f -= P[layout.seat_param("c3", s)] * (vel[..., d[key]] - (v2 + x * om + y * w_ph))
        force[key] += f
        on_body(-f, x, y)
    for j, w in enumerate(layout.wheels):
        key = f"z1{w}"
        x = P["l_f"] if w.startswith("f") else -P["l_b"]
        y = 0.0 if not layout.full else (P["w_r"] if w.endswith("r") else -P["w_l"])
        f = P[f"k2{w}"] * ((z2 + x * th + y * ph) - disp[..., d[key]]) + P[f"c2{w}"] * (
            (v2 + x * om + y * w_ph) - vel[..., d[key]]
        )
        force[key] += f - P[f"k1{w}"] * (disp[..., d[key]] - road[..., j])
        if road_vel is not None:
            force[key] -= P[f"c1{w}"] * (vel[..., d[key]] - road_vel[..., j])
        on_body(-f, x, y)
    mass = {f"z3{layout.suffix(s)}": P[layout.seat_param("m3", s)] for s in layout.seat_names}
    mass.update({"z2": P["m2"], "pitch": P["I_pitch"], **{f"z1{w}": P[f"m1{w}"] for w in layout.wheels}})
    if layout.full:
        mass["roll"] = P["I_roll"]
    return np.stack([accel[..., d[n]] - force[n] / mass[n] for n in layout.dofs], -1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path")
    parser.add_argument("--split", default="test")
    parser.add_argument("--block", type=int, default=200)
    args = parser.parse_args()
    from hybridqcm.data.hdf5 import dataset_info

    info = dataset_info(args.path)
    layout = VehicleLayout.from_description(json.loads(info["attrs"]["layout"]))
    n = info["splits"][args.split]["n_samples"]
    keys = ("accel", "vel", "disp", "road", "physical") + (("road_vel",) if layout.tyre_damping else ())
    worst = np.zeros(layout.n_dof)
    for start in range(0, n, args.block):
        a = read_split(args.path, args.split, keys, index=slice(start, min(n, start + args.block)))
        accel = a["accel"].astype(np.float64)
        residual = force_balance(layout, a["physical"], accel, a["vel"], a["disp"], a["road"], a.get("road_vel"))
        rms = np.sqrt((accel**2).mean(1, keepdims=True))
        worst = np.maximum(worst, (np.abs(residual) / rms).max((0, 1)))
    print(f"{args.path} /{args.split}: {n} recordings x {info['splits'][args.split]['n_steps']} samples")
    for name, value in zip(layout.dofs, worst):
        print(f"  {name:14s} max |residual| / RMS(a) = {value:.2e}")
    print(f"worst {worst.max():.2e} (target <= 1e-6): {'met' if worst.max() <= 1e-6 else 'NOT met'}")


if __name__ == "__main__":
    main()
