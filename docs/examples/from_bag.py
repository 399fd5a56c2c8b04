"""From a robot's ROS bag to a plot: 3 s of the real iCub walk, each foot's vertical force.

``ff.load_recording`` imports a raw bag through a robot configuration (here the identified iCub,
see docs/real-logs.md); ``window`` keeps 3 s of it.  The plot shows the batch smoother's vertical
force of each foot beside the one the F/T sensors measure (the F/T readings are not given to the
estimator here).  Run from the repository: ``python docs/examples/from_bag.py [BAG]`` (the iCub
walk of ../shared/data/icub by default; writes from_bag.png; a few seconds).
"""

import sys

import matplotlib.pyplot as plt

import flexforce as ff

bag = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/icub/icub-walk-12s"
rec = ff.load_recording(bag, robot="icub-identified").window(3.0, 6.0)
est = ff.run_estimator("batch", rec)

fig, axes = plt.subplots(len(rec.contact_names), 1, sharex=True, figsize=(8, 5))
for i, (ax, foot) in enumerate(zip(axes, rec.contact_names)):
    ax.plot(rec.time, rec.ft[:, i, 2], "k", lw=0.8, label="F/T sensor")
    ax.plot(rec.time, est.wrench[:, i, 2], label="batch smoother")
    ax.set(ylabel=f"{foot} F_z [N]")
axes[0].set_title(f"iCub walk, {rec.time[-1]:.1f} s from {bag}")
axes[0].legend()
axes[-1].set_xlabel("time [s]")
fig.tight_layout()
fig.savefig("from_bag.png", dpi=100)
