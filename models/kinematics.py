"""Batched kinematics of any serial-chain arm from its URDF, with pytorch-kinematics.

``ArmKinematics`` loads a URDF, extracts the serial chain from a base link to an
end-effector link (``pytorch_kinematics.SerialChain``; branches elsewhere in the tree, e.g.
gripper fingers, are ignored) and gives, batched over configurations ``q: [B, n]``:

* the end-effector position ``[B, 3]`` (m, in the base link's frame),
* the geometric Jacobian ``[B, 6, n]`` (``chain.jacobian``: linear rows first),
* both from one forward-kinematics pass (``ArmKinematics.position_and_jacobian``), the
  call the tracking IK (``dipole_torch.models.tracking``) makes at every time step.

Everything is differentiable in ``q`` (pytorch-kinematics attaches an analytical backward to
its forward kinematics; the Jacobian is built from those poses with torch ops), so rewards of
tracked paths can be differentiated back to the policy parameters.

Joints on the chain may be revolute, continuous (unlimited revolute) or prismatic.

Loading a vendor's file
-----------------------
The file is read here first (``read_urdf_tree``), and pytorch-kinematics gets a copy
holding only what kinematics uses:

* The links and joints must form one tree: every joint names a parent and a child link that
  exist, no link is the child of two joints, one root link. A ``ValueError`` names the joint
  and the missing link otherwise (a joint whose parent is missing would otherwise cut its
  subtree off, and its links would look absent).
* Elements kinematics never reads are dropped: every top-level element but ``<link>`` and
  ``<joint>`` (``<transmission>``, ``<gazebo>``, ``<material>``, ``<ros2_control>``, ...),
  everything inside a ``<link>`` but its ``<origin>`` (visuals, collisions, inertials:
  ``package://`` meshes are never opened) and a joint's ``<dynamics>``,
  ``<safety_controller>`` and ``<calibration>``. So a transmission whose reduction is not a
  number, or a material pytorch-kinematics does not know, does not stop or clutter loading.
  A joint's ``<limit>`` and ``<mimic>`` are read here (below) and dropped from the copy too.
* What pytorch-kinematics still reports about the rest (an unknown tag or attribute inside
  a joint, perhaps a typo) comes as a ``UserWarning`` naming the file, and any parse error
  as a ``ValueError`` naming the file.
* A joint of a type pytorch-kinematics lacks (``floating``, ``planar``) off the chain is
  taken as fixed (it moves nothing on the chain); on the chain it is an error.
* A movable joint without ``<axis>`` turns about (or slides along) x, URDF's default
  (pytorch-kinematics would take z); an axis of zeros is an error.
* On the chain, a joint's axis and ``<origin xyz=... rpy=...>`` (and a link's ``<origin>``,
  which pytorch-kinematics applies) must be finite numbers: NaN or inf would make positions
  NaN, which no later check sees. A ``ValueError`` names the file and the joint or link.
* A chain without a movable joint (a file without joints too) is a ``ValueError``.
* A mimic joint on the chain is an error (pytorch-kinematics would move it as a joint of
  its own); off the chain (e.g. a gripper's second finger) it is ignored.
* An unexpanded xacro file is an error that says to run ``xacro`` first.

Joint limits (rad, or m for prismatic joints) come from the URDF unless ``joint_lower`` /
``joint_upper`` override them:

* a continuous joint: ``(-inf, inf)``, whatever its ``<limit>`` tag says (URDF gives a
  continuous joint no position limits; its tag carries effort and velocity);
* a revolute or prismatic joint: its tag's ``lower`` and ``upper``; one of them missing is
  0, URDF's default (``<limit upper="2.6" .../>`` is ``[0, 2.6]``);
* both missing: a ``ValueError`` naming the joint, unless both overrides are given.
  URDF's defaults would lock the joint at ``[0, 0]`` and the arm would silently lose a
  degree of freedom; a joint meant not to move is written ``fixed``;
* a revolute or prismatic joint without a ``<limit>`` tag (URDF requires one):
  ``(-inf, inf)``, as pytorch-kinematics reads it;
* a limit that is not a number (NaN included), a lower limit of +inf or an upper one of
  -inf, in the URDF or the overrides: a ``ValueError`` naming the joint.

The chain's joints (``ArmKinematics.chain``) carry the limits the arm uses.
"""

from __future__ import annotations

import contextlib
import difflib
import math
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from xml.etree import ElementTree

import torch
from torch import Tensor

# The repository root; in a wheel, the installed dipole_torch/ folder, which holds models/ there
# too (pyproject.toml), so models/wam/wam7.urdf resolves either way.
PROJECT_ROOT = Path(__file__).resolve().parents[1]


def resolve_urdf_path(urdf: str | Path) -> Path:
    """The URDF file ``urdf`` names: an absolute path, or a path relative to the current
    directory or else to the project root (so ``models/wam/wam7.urdf`` works from anywhere).
    Raises ``FileNotFoundError`` naming the places tried."""
    path = Path(urdf).expanduser()
    candidates = [path] if path.is_absolute() else [Path.cwd() / path, PROJECT_ROOT / path]
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    tried = ", ".join(str(c) for c in candidates)
    raise FileNotFoundError(f"urdf: no file {str(urdf)!r} (tried {tried})")


URDF_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")
CHAIN_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")  # pytorch-kinematics'
# A joint's elements the copy for pytorch-kinematics leaves out: read here (limit, mimic) or
# never needed for kinematics (and a source of parse errors in vendors' files).
_JOINT_ELEMENTS_DROPPED = frozenset(
    {"limit", "mimic", "dynamics", "safety_controller", "calibration"}
)
_LIMIT_ATTRIBUTES = frozenset({"lower", "upper", "effort", "velocity"})


class UrdfTree:
    """The links and joints of a URDF file, checked to form one tree.

    Attributes:
        path: the file.
        robot_name: its ``<robot name=...>`` (the file's stem if it has none).
        root_link: the one link that is no joint's child.
        links: link names, depth first from the root (children in the file's joint order).
        joints: ``{name: <joint> element}`` in file order.
        parent_joint: ``{link: name of the joint whose child it is}`` for every link but
            the root.
    """

    def __init__(self, robot: ElementTree.Element, path: Path):
        self.path = path
        self.robot_name = robot.get("name") or path.stem
        self.links = []
        self.joints: dict[str, ElementTree.Element] = {}
        self.parent_joint: dict[str, str] = {}
        self._robot = robot
        file = path.name
        declared = []
        for link in robot.findall("link"):
            name = link.get("name")
            if not name:
                raise ValueError(f"urdf {path}: a <link> has no name")
            if name in declared:
                raise ValueError(f"urdf {path}: link {name!r} is defined twice")
            declared.append(name)
        if not declared:
            raise ValueError(f"urdf {path}: no <link> elements (is it a URDF file?)")
        children: dict[str, list[str]] = {name: [] for name in declared}
        for joint in robot.findall("joint"):
            name = joint.get("name")
            if not name:
                raise ValueError(f"urdf {path}: a <joint> has no name")
            if name in self.joints:
                raise ValueError(f"urdf {path}: joint {name!r} is defined twice")
            kind = joint.get("type")
            if kind not in URDF_JOINT_TYPES:
                raise ValueError(
                    f"urdf {path}: joint {name!r} has type {kind!r}; URDF's joint types are "
                    f"{', '.join(URDF_JOINT_TYPES)}"
                )
            ends = {}
            for end in ("parent", "child"):
                element = joint.find(end)
                link = element.get("link") if element is not None else None
                if not link:
                    raise ValueError(f'urdf {path}: joint {name!r} has no <{end} link="..."/>')
                if link not in children:
                    close = difflib.get_close_matches(link, declared, n=1)
                    hint = f" (did you mean {close[0]!r}?)" if close else ""
                    raise ValueError(
                        f"urdf {path}: joint {name!r} names {end} link {link!r}, which is not a "
                        f"link of {file}{hint}"
                    )
                ends[end] = link
            parent, child = ends["parent"], ends["child"]
            if child in self.parent_joint:
                raise ValueError(
                    f"urdf {path}: link {child!r} is the child of two joints, "
                    f"{self.parent_joint[child]!r} and {name!r}"
                )
            if child == parent:
                raise ValueError(f"urdf {path}: joint {name!r} joins link {child!r} to itself")
            self.joints[name] = joint
            self.parent_joint[child] = name
            children[parent].append(child)
        roots = [name for name in declared if name not in self.parent_joint]
        if len(roots) != 1:
            raise ValueError(
                f"urdf {path}: "
                + (
                    f"{len(roots)} root links (links that are no joint's child): "
                    f"{', '.join(roots)}; a URDF is one tree with one root"
                    if roots
                    else "every link is a joint's child: the joints form a loop"
                )
            )
        self.root_link = roots[0]
        stack = [self.root_link]
        while stack:  # depth first, children in the file's joint order
            link = stack.pop()
            self.links.append(link)
            stack.extend(reversed(children[link]))
        if len(self.links) != len(declared):
            loop = [name for name in declared if name not in set(self.links)]
            raise ValueError(
                f"urdf {path}: the joints form a loop through links {', '.join(loop)} (not "
                f"connected to the root link {self.root_link!r})"
            )

    def parent_link(self, link: str) -> str | None:
        """The parent link of ``link`` (``None`` for the root)."""
        joint = self.parent_joint.get(link)
        return None if joint is None else self.joints[joint].find("parent").get("link")

    def chain_joints(self, base_link: str, end_effector: str) -> list[str] | None:
        """Names of the joints from ``base_link`` down to ``end_effector`` (fixed ones
        included), or ``None`` if ``end_effector`` is not below ``base_link``."""
        joints, link = [], end_effector
        while link != base_link:
            if link not in self.parent_joint:
                return None
            joints.append(self.parent_joint[link])
            link = self.parent_link(link)
        return joints[::-1]

    def kinematic_copy(self) -> bytes:
        """The file as pytorch-kinematics gets it: links and joints only, without the
        elements kinematics does not read (module docstring). A joint of a type
        pytorch-kinematics lacks becomes fixed (``ArmKinematics`` rejects one on its
        chain); a movable joint without ``<axis>`` gets URDF's default x axis."""
        robot = ElementTree.Element("robot", name=self.robot_name)
        for link in self._robot.findall("link"):
            copy = ElementTree.SubElement(robot, "link", name=link.get("name"))
            copy.extend(link.findall("origin"))  # pytorch-kinematics applies a link's origin
        for joint in self.joints.values():
            copy = ElementTree.SubElement(robot, "joint", dict(joint.attrib))
            copy.extend(child for child in joint if child.tag not in _JOINT_ELEMENTS_DROPPED)
            kind = joint.get("type")
            if kind not in CHAIN_JOINT_TYPES:
                copy.set("type", "fixed")
            elif kind != "fixed" and copy.find("axis") is None:
                ElementTree.SubElement(copy, "axis", xyz="1 0 0")  # URDF's default axis
        return ElementTree.tostring(robot)

    def joint_limits(self, name: str) -> tuple[float | None, float | None]:
        """``(lower, upper)`` of joint ``name`` from the URDF (module docstring): ``±inf``
        for a continuous joint or a joint without ``<limit>``; ``None`` for a missing
        ``lower`` / ``upper`` attribute of a revolute or prismatic joint's ``<limit>``."""
        joint = self.joints[name]
        limit = joint.find("limit")
        if joint.get("type") == "continuous" or limit is None:
            return -math.inf, math.inf
        unknown = sorted(set(limit.attrib) - _LIMIT_ATTRIBUTES)
        if unknown:
            warnings.warn(
                f"urdf {self.path}: joint {name!r}: unknown <limit> attribute(s) "
                f"{', '.join(unknown)} (URDF's are effort, lower, upper, velocity)",
                stacklevel=3,
            )
        values = []
        for side, sign in (("lower", -1), ("upper", 1)):
            text = limit.get(side)
            try:
                value = None if text is None else float(text)
            except ValueError:
                value = math.nan
            # NaN would pass every comparison (a limit check, the reach) and reach the rollouts
            if value is not None and (math.isnan(value) or value == -sign * math.inf):
                raise ValueError(
                    f"urdf {self.path}: joint {name!r} has <limit {side}={text!r}>, "
                    + ("not a number" if math.isnan(value) else "which leaves the joint no value")
                )
            values.append(value)
        return values[0], values[1]

    def link(self, name: str) -> ElementTree.Element:
        """The ``<link>`` element named ``name``."""
        return next(link for link in self._robot.findall("link") if link.get("name") == name)


def read_urdf_tree(path: Path) -> UrdfTree:
    """The checked ``UrdfTree`` of the URDF file ``path``. Raises ``ValueError`` naming
    the file for invalid XML, an unexpanded xacro file or links and joints that are not one
    tree (naming the joint and the link)."""
    try:
        robot = ElementTree.fromstring(path.read_bytes())
    except ElementTree.ParseError as error:
        raise ValueError(f"urdf {path} is not valid XML: {error}") from None
    if any(element.tag.startswith("{") and "xacro" in element.tag for element in robot.iter()):
        raise ValueError(
            f"urdf {path} is a xacro file (it holds xacro: elements): expand it first, e.g. "
            f"`xacro {path.name} > {path.stem.removesuffix('.urdf')}.urdf`"
        )
    if robot.tag != "robot":
        raise ValueError(f"urdf {path}: its root element is <{robot.tag}>, not <robot>")
    return UrdfTree(robot, path)


def _three_numbers(text: str) -> list[float] | None:
    """The three numbers of an ``xyz`` / ``rpy`` attribute, or ``None`` if it is not three
    numbers."""
    try:
        values = [float(x) for x in text.split()]
    except ValueError:
        return None
    return values if len(values) == 3 else None


def _check_origin(origin: ElementTree.Element, where: str) -> None:
    """Raise a ``ValueError`` starting with ``where`` unless the ``xyz`` and ``rpy`` of
    ``origin`` (each 0 0 0 if missing) are three finite numbers: NaN or inf would make every
    position past it NaN, which no later check sees (comparisons with NaN are False)."""
    for attribute in ("xyz", "rpy"):
        text = origin.get(attribute)
        if text is None:
            continue
        values = _three_numbers(text)
        if values is None or not all(map(math.isfinite, values)):
            raise ValueError(
                f"{where} has <origin {attribute}={text!r}>; an origin's {attribute} is three "
                "finite numbers"
            )


@contextlib.contextmanager
def _urdf_messages_as_warnings(path: Path) -> Iterator[None]:
    """pytorch-kinematics' URDF parser writes what it skips ('Unknown tag ...') to stderr;
    within this block each message is a ``UserWarning`` naming ``path`` instead."""

    from pytorch_kinematics.urdf_parser_py.xml_reflection import core as urdf_reflection

    def warn(message: str) -> None:
        warnings.warn(f"urdf {path}: {message}", stacklevel=2)

    previous = urdf_reflection.on_error
    urdf_reflection.on_error = warn
    try:
        yield
    finally:
        urdf_reflection.on_error = previous


class ArmKinematics:
    """Forward kinematics and Jacobians of a serial-chain arm, batched over configurations.

    Args:
        urdf: path of the URDF file (see ``resolve_urdf_path``).
        end_effector: name of the end-effector link (the point the task moves).
        base_link: name of the link whose frame positions are expressed in (default: the
            URDF's root link). It must be an ancestor of ``end_effector``.
        joint_lower, joint_upper: ``[n]`` joint limits (rad, or m for prismatic joints)
            overriding the URDF's; ``None`` keeps the URDF's.
        device: device of the chain and of every returned tensor.
        dtype: floating dtype of the chain (``torch.float64`` for gradient checks).

    Attributes:
        chain: the ``pytorch_kinematics.SerialChain`` from ``base_link`` to ``end_effector``.
        dof: n, the number of movable joints on the chain.
        joint_names: their names, in the order of the columns of ``q``.
        joint_lower, joint_upper: ``[n]`` joint limits.
        urdf_path: the resolved URDF file.
        robot_name: the ``<robot name=...>`` of the URDF.
    """

    def __init__(
        self,
        urdf: str | Path,
        end_effector: str,
        base_link: str | None = None,
        joint_lower: Sequence[float] | None = None,
        joint_upper: Sequence[float] | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ):
        self.device = torch.device(device)
        self.dtype = dtype
        self.urdf_path = resolve_urdf_path(urdf)
        tree = read_urdf_tree(self.urdf_path)
        self.robot_name = tree.robot_name
        file = self.urdf_path.name
        for name, value in (("end_effector", end_effector), ("base_link", base_link)):
            if value is not None and value not in tree.links:
                close = difflib.get_close_matches(value, tree.links, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ValueError(
                    f"{name} {value!r} is not a link of {file}{hint}; its links are "
                    f"{', '.join(tree.links)}"
                )
        root = tree.root_link if base_link is None else base_link
        on_chain = tree.chain_joints(root, end_effector)
        if on_chain is None:
            raise ValueError(
                f"end_effector {end_effector!r} is not below base_link {root!r} in "
                f"{file}: pick a base link on the path from the root to it"
            )
        for joint in on_chain:
            element = tree.joints[joint]
            if element.get("type") not in CHAIN_JOINT_TYPES:
                raise ValueError(
                    f"urdf {self.urdf_path}: unsupported joint type {element.get('type')!r} of "
                    f"joint {joint!r} between {root!r} and {end_effector!r} (serial chains of "
                    "revolute, continuous, prismatic and fixed joints are supported)"
                )
            for origin in element.findall("origin"):
                _check_origin(origin, f"urdf {self.urdf_path}: joint {joint!r}")
            child = element.find("child").get("link")
            for origin in tree.link(child).findall("origin"):  # pytorch-kinematics applies it
                _check_origin(origin, f"urdf {self.urdf_path}: link {child!r}")
            axis = element.find("axis")
            if element.get("type") != "fixed" and axis is not None:
                text = axis.get("xyz", "")
                values = _three_numbers(text)
                # A zero, NaN or infinite axis would give NaN positions (normalised axis).
                if values is None or not all(map(math.isfinite, values)) or not any(values):
                    raise ValueError(
                        f"urdf {self.urdf_path}: joint {joint!r} has <axis xyz={text!r}>; a "
                        "movable joint's axis is three finite numbers, not all zero"
                    )
            mimic = element.find("mimic")
            if mimic is not None:
                raise ValueError(
                    f"urdf {self.urdf_path}: joint {joint!r} between {root!r} and "
                    f"{end_effector!r} mimics joint {mimic.get('joint')!r}; a chain with mimic "
                    "joints is not supported (it would move as a joint of its own): pick an "
                    f"end effector above it, e.g. {tree.joints[joint].find('parent').get('link')!r}"
                )
        if not any(tree.joints[joint].get("type") != "fixed" for joint in on_chain):
            # Checked before pytorch-kinematics builds the chain: it fails on a file without
            # joints (UnboundLocalError), and a chain of fixed joints moves nothing.
            raise ValueError(f"no movable joint between {root!r} and {end_effector!r} in {file}")
        self.base_link = root
        self.end_effector = end_effector
        # Imported here: pytorch-kinematics (with matplotlib and scipy) takes longer to import
        # than a run of train.py needs before its first ask, and --help needs none of it.
        import pytorch_kinematics as pk
        from pytorch_kinematics.urdf_parser_py.xml_reflection import core as urdf_reflection

        try:
            with _urdf_messages_as_warnings(self.urdf_path):
                full_chain = pk.build_chain_from_urdf(tree.kinematic_copy())
        except urdf_reflection.ParseError as error:
            raise ValueError(f"urdf {self.urdf_path}: {error}") from None
        chain = pk.SerialChain(full_chain, end_effector, "" if base_link is None else base_link)
        self.chain = chain.to(device=self.device, dtype=dtype)
        self.joint_names = list(self.chain.get_joint_parameter_names())
        self.dof = len(self.joint_names)
        lower, upper = self._urdf_limits(tree, joint_lower is None or joint_upper is None)
        factory = {"device": self.device, "dtype": dtype}
        self.joint_lower = self._limit(joint_lower, lower, "joint_lower", factory)
        self.joint_upper = self._limit(joint_upper, upper, "joint_upper", factory)
        # NaN would pass every comparison below and reach the rollouts; lower = +inf or
        # upper = -inf leaves the joint no value.
        invalid = [
            f"{name} [{format_value(low)}, {format_value(high)}]"
            for name, low, high in zip(
                self.joint_names, self.joint_lower.tolist(), self.joint_upper.tolist(), strict=True
            )
            if math.isnan(low) or math.isnan(high) or low == math.inf or high == -math.inf
        ]
        if invalid:
            raise ValueError(
                f"joint limits: not numbers (NaN) or infinite the wrong way (lower +inf, upper "
                f"-inf) for joint(s) {', '.join(invalid)} of {file}"
            )
        crossed = [
            f"{name} [{format_value(low)}, {format_value(high)}]"
            for name, low, high in zip(
                self.joint_names, self.joint_lower.tolist(), self.joint_upper.tolist(), strict=True
            )
            if not low <= high
        ]
        if crossed:
            raise ValueError(
                f"joint limits: lower exceeds upper for joint(s) {', '.join(crossed)} of "
                f"{file} (rad, or m for prismatic joints)"
            )
        # The chain's own limits, for users of arm.chain: the ones this arm uses.
        for joint, low, high in zip(
            self.chain.get_joints(),
            self.joint_lower.tolist(),
            self.joint_upper.tolist(),
            strict=True,
        ):
            joint.limits = (low, high)

    def _urdf_limits(self, tree: UrdfTree, needed: bool) -> tuple[list[float], list[float]]:
        """``[n]`` lower and upper limits of the chain's joints from the URDF (module
        docstring); ``needed``: some side is not overridden, so a joint whose ``<limit>``
        gives neither is an error."""
        lower, upper = [], []
        for name in self.joint_names:
            low, high = tree.joint_limits(name)
            if low is None and high is None and needed:
                raise ValueError(
                    f"urdf {self.urdf_path}: joint {name!r} is {tree.joints[name].get('type')} "
                    "but its <limit> gives neither lower nor upper; URDF's defaults would lock "
                    "it at [0, 0]. Give lower and upper in the tag (or make the joint "
                    "continuous or fixed), or pass joint_lower and joint_upper"
                )
            lower.append(0.0 if low is None else low)  # URDF's default for a missing side
            upper.append(0.0 if high is None else high)
        return lower, upper

    def _limit(self, given, from_urdf, name: str, factory: dict) -> Tensor:
        try:
            values = from_urdf if given is None else [float(v) for v in given]
        except (TypeError, ValueError):
            raise ValueError(
                f"{name} must be {self.dof} numbers (joints {', '.join(self.joint_names)}), "
                f"got {given!r}"
            ) from None
        if len(values) != self.dof:
            raise ValueError(
                f"{name} must give {self.dof} values (joints {', '.join(self.joint_names)}), "
                f"got {len(values)}"
            )
        return torch.as_tensor(values, **factory)

    def check_joints(self, q: Tensor) -> Tensor:
        """Validate ``q: [B, n]`` and move it to the chain's device and dtype."""
        if not isinstance(q, Tensor):
            raise TypeError(f"q must be a torch.Tensor, got {type(q).__name__}")
        if q.dim() != 2 or q.shape[-1] != self.dof:
            raise ValueError(
                f"q must have shape [B, {self.dof}] (joints {', '.join(self.joint_names)}), "
                f"got {list(q.shape)}"
            )
        return q.to(device=self.device, dtype=self.dtype)

    def forward_kinematics(self, q: Tensor) -> Tensor:
        """End-effector positions ``[B, 3]`` (m, base frame) of joint values ``q: [B, n]``."""
        return self.position_and_jacobian(q)[0]

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobians ``[B, 6, n]`` (linear rows first) in the base frame."""
        return self.chain.jacobian(self.check_joints(q))

    def position_and_jacobian(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Positions ``[B, 3]`` and position Jacobians ``[B, 3, n]`` of ``q: [B, n]`` from one
        pytorch-kinematics forward pass (``chain.jacobian(q, ret_eef_pose=True)``)."""
        jacobian, pose = self.chain.jacobian(self.check_joints(q), ret_eef_pose=True)
        return pose[:, :3, 3], jacobian[:, :3]

    def clamp_to_limits(self, q: Tensor) -> Tensor:
        """``q: [..., n]`` clamped into the joint limits."""
        return torch.maximum(torch.minimum(q, self.joint_upper), self.joint_lower)

    def middle_posture(self) -> Tensor:
        """``[n]`` joint values halfway between the limits (0 for an unlimited joint)."""
        middle = 0.5 * (self.joint_lower + self.joint_upper)
        return torch.where(torch.isfinite(middle), middle, torch.zeros_like(middle))


def format_value(value: float) -> str:
    """A joint value or limit for a message: 4 significant digits, so that float32 limits
    print as the URDF wrote them (``2.6``, not ``2.5999999046325684``)."""
    return f"{value:.4g}"
