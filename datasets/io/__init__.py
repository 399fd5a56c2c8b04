"""flexforce.datasets.io: recordings in and estimates out.

ROS bags (:mod:`.bagio` for flexforce's own bags, :mod:`.rosimport` for a robot's bags, :mod:`.stream`
for importing a bag part by part in constant memory), the local frame from the joint encoders
(:mod:`.localframe`), exports (:mod:`.export`, :mod:`.csvformat`) and viewer layouts (:mod:`.viewers`).
Imports only the data types, the robot model and the errors.
"""
