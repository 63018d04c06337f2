"""Inverse kinematics of a boom-arm-bucket chain, closed form and vectorised over frames.

A shovel's or excavator's digging linkage is planar: boom, arm and bucket turn about pins
parallel to the house's y axis. In the house's x-z plane (x forward, z up) each link has
an upward angle ``phi`` (rad, from the house's x axis), the sum of its pin's fixed pitch
offset and the joint values of it and its ancestors. The bucket tip is

    tip = pin + R(phi_boom) d_arm + R(phi_arm) d_bucket + R(phi_bucket) d_tip

with ``R(phi)`` the upward rotation in the plane and ``d_*`` the (x, z) offsets from the
model (arm pin in the boom's frame, bucket pin in the arm's frame, tip in the bucket's
frame). Given the tip and the bucket angle, the bucket pin follows; the boom and arm are a
two-link problem solved by the law of cosines, on the elbow side of the joint limits'
middle pose.

Shapes: F frames, J joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.machine import REVOLUTE, Machine
from mocap.errors import InputError


@dataclass(frozen=True)
class PlanarChain:
    """The boom-arm-bucket linkage of a machine, in its house's x-z plane.

    `joints` (3,) joint indices of boom, arm, bucket; `swing` the house's joint index;
    `pin` (2,) boom pin (x, z) in the house frame; `offsets` (3, 2) arm pin in the boom,
    bucket pin in the arm, tip in the bucket (x, z); `pitch` (3,) upward angle of each
    link frame at joint value 0 relative to its parent (rad); `sign` (3,) +1 where a
    positive joint value turns the link upward; `angle_offset` the upward angle of the
    bucket-angle direction in the bucket frame; `elbow` +1 or -1; `house_height` the
    height of the house frame above the base (m).
    """

    joints: tuple[int, int, int]
    swing: int
    pin: np.ndarray
    offsets: np.ndarray
    pitch: np.ndarray
    sign: np.ndarray
    angle_offset: float
    elbow: float
    house_height: float
    n_joints: int

    @classmethod
    def from_machine(cls, machine: Machine) -> PlanarChain:
        """The chain of `machine`; InputError if it has no boom-arm-bucket linkage."""
        if machine.bucket_angle is None or "bucket_tip" not in machine.point_names:
            raise InputError(
                "planned digs need a [bucket_angle] and a 'bucket_tip' point in the model; "
                "use a shovel or excavator model such as hitachi_ex3500",
                path=machine.name,
            )
        house = machine.house_link
        chain = machine.ancestors(machine.bucket_angle.link)
        if house not in chain or chain.index(house) != 3:
            raise InputError(
                "planned digs need boom, arm and bucket links between the house and the "
                "bucket-angle link",
                path=machine.name,
            )
        links = chain[:3][::-1]  # boom, arm, bucket
        joint_of = {link: j for j, link in enumerate(machine.joint_links)}
        house_joint = machine.links[house].joint
        if house_joint is None or house_joint.type != REVOLUTE or abs(house_joint.axis[2]) < 0.999:
            raise InputError("planned digs need a house that swings about the vertical", path=machine.name)
        pitch, sign, origins = [], [], []
        for link in links:
            joint = machine.links[link].joint
            planar = (
                joint.type == REVOLUTE
                and abs(abs(joint.axis[1]) - 1.0) < 1e-9
                and abs(joint.origin[1]) < 1e-9
                and abs(joint.rpy[0]) < 1e-12
                and abs(joint.rpy[2]) < 1e-12
            )
            if not planar:
                raise InputError(
                    f"joint {joint.name!r} does not turn about the house's y axis; planned "
                    "digs need a planar boom-arm-bucket linkage",
                    path=machine.name,
                )
            pitch.append(-joint.rpy[1])  # Ry(pitch) turns x downward
            sign.append(-np.sign(joint.axis[1]))  # about -y turns x upward
            origins.append(joint.origin[[0, 2]])
        k = machine.point_names.index("bucket_tip")
        if machine.point_links[k] != links[2]:
            raise InputError("'bucket_tip' must be a point of the bucket-angle link", path=machine.name)
        tip = machine.point_positions[k][[0, 2]]
        direction = machine.bucket_angle.direction
        chain_obj = cls(
            joints=tuple(joint_of[link] for link in links),
            swing=joint_of[house],
            pin=origins[0],
            offsets=np.array([origins[1], origins[2], tip]),
            pitch=np.array(pitch),
            sign=np.array(sign),
            angle_offset=float(np.arctan2(direction[2], direction[0])),
            elbow=1.0,
            house_height=float(house_joint.origin[2]),
            n_joints=machine.n_joints,
        )
        mid = machine.joint_limits[list(chain_obj.joints)].mean(axis=1)
        phi = chain_obj.link_angles(mid[None])[0]
        alpha = np.arctan2(chain_obj.offsets[:2, 1], chain_obj.offsets[:2, 0])
        bend = _wrap((phi[1] + alpha[1]) - (phi[0] + alpha[0]))
        object.__setattr__(chain_obj, "elbow", 1.0 if bend >= 0 else -1.0)
        return chain_obj

    def link_angles(self, planar_joints: np.ndarray) -> np.ndarray:
        """Upward angles of boom, arm and bucket (F, 3) for their joint values (F, 3)."""
        return np.cumsum(self.pitch + self.sign * np.asarray(planar_joints, dtype=float), axis=-1)

    def forward(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tip (F, 2) in the house's x-z plane and bucket angle (F,) for joints (F, J)."""
        phi = self.link_angles(np.asarray(joints)[:, list(self.joints)])
        tip = self.pin + sum(_turn(phi[:, i], self.offsets[i]) for i in range(3))
        return tip, _wrap(phi[:, 2] + self.angle_offset)

    def reachable(self, tip: np.ndarray, bucket_angle: np.ndarray, limits: np.ndarray | None = None,
                  margin: float = 0.0) -> np.ndarray:
        """(F,) whether the tip at `tip` (F, 2) with `bucket_angle` (F,) rad is reached with
        the boom-arm reach to spare by `margin` (a share of its length) and, given `limits`
        (J, 2) rad / m of all joints, with boom, arm and bucket inside them."""
        wrist = self._wrist(np.asarray(tip, dtype=float), np.asarray(bucket_angle, dtype=float))
        l1, l2 = np.linalg.norm(self.offsets[:2], axis=1)
        distance = np.linalg.norm(wrist, axis=-1)
        ok = (distance <= (1.0 - margin) * (l1 + l2)) & (distance >= abs(l1 - l2) + margin * (l1 + l2))
        if limits is None or not ok.any():
            return ok
        joints = self.inverse(np.asarray(tip)[ok], np.asarray(bucket_angle)[ok], np.zeros(int(ok.sum())))
        planar = list(self.joints)
        inside = (joints[:, planar] >= limits[planar, 0] - 1e-9) & (joints[:, planar] <= limits[planar, 1] + 1e-9)
        ok[ok] = inside.all(axis=1)
        return ok

    def _wrist(self, tip: np.ndarray, bucket_angle: np.ndarray) -> np.ndarray:
        """The bucket pin (F, 2) from the boom pin for a tip (F, 2) and bucket angle (F,)."""
        return tip - _turn(bucket_angle - self.angle_offset, self.offsets[2]) - self.pin

    def inverse(self, tip: np.ndarray, bucket_angle: np.ndarray, swing: np.ndarray) -> np.ndarray:
        """Joint values (F, J) that put the tip at `tip` (F, 2) (house x-z plane, m) with
        the bucket angle `bucket_angle` (F,) rad and the house at `swing` (F,) rad.

        Raises ValueError naming the first frame whose tip is out of reach.
        """
        tip = np.asarray(tip, dtype=float)
        phi_bucket = np.asarray(bucket_angle, dtype=float) - self.angle_offset
        wrist = self._wrist(tip, np.asarray(bucket_angle, dtype=float))  # bucket pin from boom pin
        l1, l2 = np.linalg.norm(self.offsets[:2], axis=1)
        alpha = np.arctan2(self.offsets[:2, 1], self.offsets[:2, 0])
        reach2 = np.einsum("fi,fi->f", wrist, wrist)
        cos_bend = (reach2 - l1**2 - l2**2) / (2 * l1 * l2)
        bad = np.flatnonzero(np.abs(cos_bend) > 1.0)
        if bad.size:
            raise ValueError(
                f"tip out of reach at frame {bad[0]} ({np.sqrt(reach2[bad[0]]):.2f} m from the "
                f"boom pin, reach {abs(l1 - l2):.2f}..{l1 + l2:.2f} m)"
            )
        bend = self.elbow * np.arccos(cos_bend)
        psi1 = np.arctan2(wrist[:, 1], wrist[:, 0]) - np.arctan2(l2 * np.sin(bend), l1 + l2 * np.cos(bend))
        phi = np.stack([psi1 - alpha[0], psi1 + bend - alpha[1], phi_bucket], axis=-1)
        relative = np.diff(phi, axis=-1, prepend=0.0) - self.pitch
        joints = np.zeros((len(tip), self.n_joints))
        joints[:, list(self.joints)] = _wrap(relative) * self.sign
        joints[:, self.swing] = swing
        return joints


def _turn(angle: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Offsets (x, z) (2,) turned upward by `angle` (F,) -> (F, 2)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]], axis=-1)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi
