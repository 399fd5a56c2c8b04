"""From your own arrays to a plot: a robot of 40 kg standing on two feet, its CoM swaying sideways.

Every array is one row per step of a uniform 200 Hz grid (``ff.Recording.from_arrays`` lists
them with their frames and units); the IMU reads gravity alone (the robot is rigid and still but
for its CoM).  The batch smoother shares the weight between the feet (their vertical forces and
their torques); the plot shows each foot's vertical force following the CoM from one foot to the
other.  Run: ``python from_arrays.py`` (writes from_arrays.png; a few seconds).
"""

import matplotlib.pyplot as plt
import numpy as np

import flexforce as ff

t = np.arange(600) * 0.005  # 3 s at 200 Hz
n, w = len(t), 2 * np.pi * 0.5  # a 0.5 Hz sway of 3 cm
com = np.column_stack([0 * t, 0.03 * np.sin(w * t), 0 * t + 0.8])
com_acc = np.column_stack([0 * t, -0.03 * w**2 * np.sin(w * t), 0 * t])
zeros, eye = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1))
rec = ff.Recording.from_arrays(
    np.round(t * 1e9).astype(np.int64), robot="romeo", contact_names=["left_foot", "right_foot"], mass=40.0,
    com=com, com_vel=np.gradient(com, t, axis=0), com_acc=com_acc, inertia=eye * [4.0, 4.0, 0.5],
    inertia_dot=0 * eye, sigma=zeros, sigma_dot=zeros, imu_R=eye, imu_p=zeros + [0, 0, 1.0], imu_v=zeros,
    imu_a=zeros, imu_w=zeros, contact_active=np.ones((n, 2), bool), contact_p=np.stack(
        [zeros + [0, 0.1, 0], zeros + [0, -0.1, 0]], axis=1), contact_R=np.stack([eye, eye], axis=1),
    gyro=zeros, accel=zeros + [0, 0, 9.81])
est = ff.run_estimator("batch", rec)

fig, ax = plt.subplots(figsize=(8, 3.5))
for i, foot in enumerate(rec.contact_names):
    ax.plot(rec.time, est.wrench[:, i, 2], label=f"{foot} (batch smoother)")
ax.set(xlabel="time [s]", ylabel="vertical force F_z [N]", title="Weight shifting between the feet")
ax.legend()
fig.tight_layout()
fig.savefig("from_arrays.png", dpi=100)
