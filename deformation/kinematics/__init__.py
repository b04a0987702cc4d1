"""Kinematics: rigid transforms, skeletons and their poses, rigid fits and dual quaternions.

* :mod:`~deformation.kinematics.transforms` — rigid 4x4 transforms in world millimetres;
* :mod:`~deformation.kinematics.skeleton` — bones, joints, forward kinematics, poses (Kurihara §3, Rhee §3.1);
* :mod:`~deformation.kinematics.rigid_fit` — least-squares rigid fits of point sets (Kabsch, Umeyama);
* :mod:`~deformation.kinematics.dual_quaternion` — unit dual quaternions for blending rigid transforms.
"""
