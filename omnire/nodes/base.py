"""Scene-graph node base classes.

A node type holds *all* actors it models (one node object per type, batched, as in the
reference implementation), so per-step cost is one gather + one transform per type.

Contract of a :class:`Node`:
- ``gaussian_params`` (ParameterDict, keys ``gaussian_keys``: :data:`omnire.gaussians.GAUSSIAN_KEYS`
  plus any per-Gaussian extras): every per-Gaussian tensor the densification strategy must
  clone, split and prune. ``gaussian_buffers``: per-Gaussian non-trainable tensors (e.g.
  owning instance), densified alongside.
- ``gaussians_at(t, camera=None, step=None)`` returns a :class:`NodeOutput` (world-space
  Gaussians of what is present at the moment ``t`` and the rows of ``gaussian_params``
  they came from), or None when nothing of the node is present (absent nodes cost
  nothing). ``camera`` is the camera being rendered: nodes with costly per-Gaussian work
  may skip Gaussians it cannot see (the rasterizer culls anyway); None means "no camera":
  return everything. ``step`` is the schedule step of training (None outside training:
  render the fully trained model); nodes use it for schedules such as warm-ups, and so
  follow a time budget like every schedule (:mod:`omnire.schedule`: it is the training step
  for a step budget).
- ``regularization(output)`` returns node-specific loss terms computed from what the node
  produced for the rendered view (nothing is kept between calls).
- ``param_groups()`` lists learning-rate groups, per-Gaussian ones by key.
- ``row_order()`` (optional): a permutation restoring the row order the node relies on
  after densification (actor nodes keep each instance's rows contiguous).
- ``lidar_features(output)``: the LiDAR features (omnire/lidarmodel.py) of an output's
  Gaussians, read from the ``lidar`` parameter by the output's ``rows``; a node built through
  :meth:`Node.init_gaussians` holds them when the method renders LiDAR, with nothing more to
  write.

:class:`GaussianNode` carries what Gaussian-holding nodes share (config, scene radius,
per-Gaussian learning rates); :class:`EnvironmentNode` is the base of nodes that paint the
image background (the sky) instead of holding Gaussians.
"""
from __future__ import annotations

import dataclasses
import weakref
from typing import Any, Callable, Optional

import torch
from torch import nn

from omnire.camera import Camera
from omnire.config import InstantiateConfig
from omnire.data.scene import SceneTime
from omnire.gaussians import GAUSSIAN_KEYS, Gaussians
from omnire.lidarmodel import LIDAR_KEY, LidarFeatures
from omnire.placement import Placement


@dataclasses.dataclass
class ParamGroup:
    """One optimiser group. ``key`` names a per-Gaussian parameter (densified) or None."""

    name: str
    params: list[nn.Parameter]
    lr: float
    lr_final: Optional[float] = None
    """If set, the lr decays exponentially from ``lr`` to ``lr_final`` over training."""
    key: Optional[str] = None
    warmup_steps: int = 0
    """Linear warm-up from 0 (used for pose refinement)."""


class NodeOutput:
    """What a node contributes to one rendered view.

    Attributes:
        gaussians: world-space Gaussians (M of them); a placed output (:meth:`placed`)
            computes them from ``local`` and ``placement`` when first read.
        rows: (M,) rows of the node's ``gaussian_params`` they came from, None = all rows in order.
        time: the moment rendered.
        extras: node-specific tensors its :meth:`Node.regularization` needs (e.g. deformed
            box-local means); nothing else reads them.
        local, placement: a placed output's box-local Gaussians (the node's own parameters
            when ``placement.starts`` picks their rows) and the per-instance poses that put
            them in the world (:class:`~omnire.placement.Placement`); None for others. A
            rasterizer that draws placed rows itself takes these and no copy is made.
    """

    def __init__(self, gaussians: Optional[Gaussians], rows: Optional[torch.Tensor], time: SceneTime,
                 extras: Optional[dict[str, Any]] = None) -> None:
        self._gaussians: Optional[Gaussians] = gaussians
        self.rows = rows
        self.time = time
        self.extras: dict[str, Any] = {} if extras is None else extras
        self.local: Optional[Gaussians] = None
        self.placement: Optional[Placement] = None

    @classmethod
    def placed(cls, local: Gaussians, placement: Placement, rows: Optional[torch.Tensor], time: SceneTime,
               extras: Optional[dict[str, Any]] = None) -> "NodeOutput":
        """An output of box-local Gaussians ``local`` put in the world by ``placement``."""
        placement.check_source(len(local))
        out = cls(None, rows, time, extras)
        out.local, out.placement = local, placement
        return out

    @property
    def gaussians(self) -> Gaussians:
        if self._gaussians is None:
            if self.placement is None:
                raise ValueError("NodeOutput has no Gaussians: pass world Gaussians, or build it with NodeOutput.placed")
            self._gaussians = self.placement.apply(self.local)
        return self._gaussians

    @property
    def num_gaussians(self) -> int:
        return self.placement.num_rows if self._gaussians is None else len(self._gaussians)

    def with_gaussians(self, gaussians: Gaussians) -> "NodeOutput":
        """The same output with world Gaussians ``gaussians`` (e.g. moved) in place of its own."""
        return NodeOutput(gaussians, self.rows, self.time, self.extras)


class Derived:
    """One value computed from tensors and kept until one of them changes: another tensor
    object, or the same one changed in place (torch's version counter counts in-place
    writes, an optimiser step's too). For what renders need every frame but only a node's
    parameters decide (e.g. how far each actor's Gaussians reach). Holds weak references to
    the tensors, so it keeps none of them alive."""

    def __init__(self) -> None:
        self._sources: tuple = ()
        self._value: Any = None

    def get(self, sources: tuple[torch.Tensor, ...], compute: Callable[[], Any]) -> Any:
        """The value of ``compute()`` for ``sources`` (computed now only when one changed)."""
        current = tuple((weakref.ref(t), t._version) for t in sources)
        if len(current) != len(self._sources) or any(
                ref() is not t or version != old for (ref, old), t, (_, version) in zip(self._sources, sources, current)):
            self._value = compute()
            self._sources = current
        return self._value


class MomentCache:
    """What a node computed for a moment at inference, kept for the next renders of that
    moment (the cameras of a rig rendered at one time share their node outputs) while the
    node's tensors hold: any parameter, buffer or per-Gaussian tensor replaced or changed
    in place (:class:`Derived`) empties it. Holds the ``size`` most recent keys."""

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._table = Derived()

    def holds(self, sources: tuple[torch.Tensor, ...], key: Any) -> bool:
        """Whether a value for ``key`` is kept for these sources."""
        return key in self._table.get(sources, dict)

    def get(self, sources: tuple[torch.Tensor, ...], key: Any, compute: Callable[[], Any]) -> Any:
        """``compute()``'s value for ``key`` (hashable: the moment and whatever else the value
        depends on besides ``sources``), computed now only when not kept for these sources."""
        table: dict = self._table.get(sources, dict)
        if key in table:
            table[key] = table.pop(key)  # most recent last
        else:
            table[key] = compute()
            while len(table) > self.size:
                del table[next(iter(table))]
        return table[key]


@dataclasses.dataclass
class NodeConfig(InstantiateConfig):
    """Base of every node config."""


@dataclasses.dataclass
class GaussianNodeConfig(NodeConfig):
    """Fields every Gaussian-holding node shares: SH degree, initial opacity and the
    per-Gaussian learning rates (reference values, docs/paper.md "Optimisation")."""

    sh_degree: int = 3
    """Highest SH degree (bands are switched on progressively by the trainer)."""
    init_opacity: float = 0.1
    """Initial opacity."""
    lr_means: float = 1.6e-4
    """Means lr (x scene radius), decaying to lr_means_final."""
    lr_means_final: float = 1.6e-6
    """Final means lr (x scene radius)."""
    lr_sh0: float = 2.5e-3
    """SH DC lr."""
    lr_shN: float = 1.25e-4
    """SH higher bands lr."""
    lr_opacity: float = 0.05
    """Opacity-logit lr."""
    lr_scales: float = 5e-3
    """Log-scale lr."""
    lr_quats: float = 1e-3
    """Quaternion lr."""

    def gaussian_lrs(self, scene_radius: float) -> dict[str, tuple[float, Optional[float]]]:
        """key -> (lr, final lr or None); means scale with the scene radius."""
        r = scene_radius
        return {"means": (self.lr_means * r, self.lr_means_final * r), "sh0": (self.lr_sh0, None),
                "shN": (self.lr_shN, None), "opacities": (self.lr_opacity, None), "scales": (self.lr_scales, None),
                "quats": (self.lr_quats, None)}


@dataclasses.dataclass
class NodeContext:
    """What a node gets when it is built.

    Attributes:
        scene: the SceneData.
        images: the ImageCache (for colouring initial points); None when restoring.
        scene_radius: scale of the scene in metres (learning rates of means scale with it).
        device: torch device.
        generator: seeded torch.Generator for initialisation.
        excluded_tracks: tracks modelled by other nodes (background must not absorb them).
        restoring: the node is built to receive a checkpoint: skip the data-driven
            initialisation (LiDAR, images, pose estimation); per-Gaussian tensors start
            empty and every persistent tensor comes from the checkpoint.
        lidar: the LiDAR features every Gaussian gets (omnire/lidarmodel.py), or None when
            the method renders no LiDAR (then no Gaussian holds any).
    """

    scene: Any
    images: Any
    scene_radius: float
    device: torch.device
    generator: torch.Generator
    excluded_tracks: list = dataclasses.field(default_factory=list)
    restoring: bool = False
    lidar: Optional[LidarFeatures] = None


class Node(nn.Module):
    """Base class: see the module docstring for the contract."""

    #: Per-Gaussian parameter keys (densified together).
    gaussian_keys: tuple[str, ...] = GAUSSIAN_KEYS

    def __init__(self) -> None:
        super().__init__()
        self.gaussian_params = nn.ParameterDict()
        self.gaussian_buffers: dict[str, torch.Tensor] = {}

    @property
    def num_gaussians(self) -> int:
        return int(self.gaussian_params["means"].shape[0]) if "means" in self.gaussian_params else 0

    def gaussians_at(self, t: SceneTime, camera: Optional[Camera] = None,
                     step: Optional[int] = None) -> Optional[NodeOutput]:
        raise NotImplementedError

    def regularization(self, output: NodeOutput) -> dict[str, torch.Tensor]:
        """Node-specific loss terms (name -> scalar) of what ``output`` rendered; weighted by
        the method config."""
        return {}

    def param_groups(self) -> list[ParamGroup]:
        return [
            ParamGroup(f"{k}", [self.gaussian_params[k]], lr, lr_final, key=k)
            for k, (lr, lr_final) in self.gaussian_lrs().items()
        ]

    def gaussian_lrs(self) -> dict[str, tuple[float, Optional[float]]]:
        """Per-Gaussian learning rates: key -> (lr, final lr or None)."""
        return {}

    def row_order(self) -> Optional[torch.Tensor]:
        """A permutation (N,) of the Gaussian rows that restores the order the node relies on
        after densification appended or removed rows, or None when the order is fine.
        Applied to every per-Gaussian tensor and optimiser moment by the strategy."""
        return None

    def extra_prune_mask(self) -> Optional[torch.Tensor]:
        """(N,) bool of Gaussians to prune for node-specific reasons (e.g. left their box)."""
        return None

    def init_gaussians(self, context: NodeContext, build: Callable[[], dict[str, torch.Tensor]]) -> None:
        """Set ``gaussian_params`` from ``build()`` (raw tensors by key), or, when restoring a
        checkpoint, to empty placeholders of every key (resized by :meth:`prepare_load`).
        With ``context.lidar`` every Gaussian also gets the LiDAR features (:data:`LIDAR_KEY`,
        initial values)."""
        if context.lidar is not None:
            self.gaussian_keys = type(self).gaussian_keys + (LIDAR_KEY,)
            self.lidar_lr = context.lidar.lr
        tensors = ({k: torch.zeros(0, device=context.device) for k in self.gaussian_keys} if context.restoring
                   else build())
        if context.lidar is not None and not context.restoring:
            means = tensors["means"]
            tensors[LIDAR_KEY] = context.lidar.initial(means.shape[0], means.device, means.dtype)
        for k in self.gaussian_keys:
            self.gaussian_params[k] = nn.Parameter(tensors[k])

    def lidar_features(self, output: NodeOutput) -> Optional[torch.Tensor]:
        """(M, 2) raw LiDAR features (omnire/lidarmodel.py) of the Gaussians of ``output``
        (one of this node's outputs: its ``rows``), or None when the node holds none.
        Gradients reach the parameter densely: (N, 2) is small next to the Gaussians."""
        if LIDAR_KEY not in self.gaussian_params:
            return None
        features = self.gaussian_params[LIDAR_KEY]
        return features if output.rows is None else features.index_select(0, output.rows)

    def set_gaussian_tensors(self, tensors: dict[str, torch.Tensor]) -> None:
        """Replace every per-Gaussian tensor (used by densification and checkpoint loading)."""
        for k, v in tensors.items():
            if k in self.gaussian_params:
                self.gaussian_params[k] = nn.Parameter(v, requires_grad=self.gaussian_params[k].requires_grad)
            else:
                self.gaussian_buffers[k] = v

    # Checkpoints: Gaussian counts change during training, so resize before loading.
    def get_extra_state(self) -> dict[str, torch.Tensor]:
        return {k: v.clone() for k, v in self.gaussian_buffers.items()}

    def set_extra_state(self, state: dict[str, torch.Tensor]) -> None:
        self.gaussian_buffers = {k: v.clone() for k, v in state.items()}

    def prepare_load(self, state_dict: dict[str, torch.Tensor], prefix: str = "") -> None:
        """Resize every parameter and buffer to the shapes in ``state_dict`` (keys under
        ``prefix``), so that ``load_state_dict`` can fill them."""
        for k in list(self.gaussian_params.keys()):
            name = f"{prefix}gaussian_params.{k}"
            if name in state_dict and state_dict[name].shape != self.gaussian_params[k].shape:
                self.gaussian_params[k] = nn.Parameter(
                    torch.empty_like(state_dict[name]), requires_grad=self.gaussian_params[k].requires_grad
                )
        for module_name, module in self.named_modules():
            sub = f"{prefix}{module_name}." if module_name else prefix
            for pname, p in list(module.named_parameters(recurse=False)):
                saved = state_dict.get(sub + pname)
                if saved is not None and saved.shape != p.shape and not pname.startswith("gaussian_params"):
                    setattr(module, pname, nn.Parameter(torch.empty_like(saved), requires_grad=p.requires_grad))
            for bname, b in list(module.named_buffers(recurse=False)):
                saved = state_dict.get(sub + bname)
                if saved is not None and b is not None and saved.shape != b.shape:
                    module._buffers[bname] = torch.empty_like(saved)


class GaussianNode(Node):
    """Base of nodes holding Gaussians: keeps the config and the scene radius, and takes the
    per-Gaussian learning rates from a :class:`GaussianNodeConfig`."""

    def __init__(self, config: GaussianNodeConfig, context: NodeContext) -> None:
        super().__init__()
        self.config = config
        self.scene_radius = context.scene_radius

    def gaussian_lrs(self) -> dict[str, tuple[float, Optional[float]]]:
        lrs = self.config.gaussian_lrs(self.scene_radius)
        if LIDAR_KEY in self.gaussian_params:
            lrs[LIDAR_KEY] = (self.lidar_lr, None)
        return lrs


class EnvironmentNode(Node):
    """Base of nodes that paint what no Gaussian covers (the sky), composited under the
    Gaussians as C = C_gs + (1 - O_gs) C_env. They hold no Gaussians."""

    def render_environment(self, camera: Camera, t: SceneTime, pixels: Optional[torch.Tensor] = None
                           ) -> torch.Tensor:
        """(H, W, 3) colour in [0, 1] of every pixel of ``camera`` at ``t``; with ``pixels``
        ((P,) int64 row-major indices y * W + x), (P, 3) the colour of those pixels only (the
        same values as the full image's at them)."""
        raise NotImplementedError

    def gaussians_at(self, t: SceneTime, camera: Optional[Camera] = None,
                     step: Optional[int] = None) -> Optional[NodeOutput]:
        return None


def init_gaussian_params(
    points: torch.Tensor,
    colors: torch.Tensor,
    scales: torch.Tensor,
    sh_degree: int,
    opacity: float,
    generator: Optional[torch.Generator] = None,
) -> dict[str, torch.Tensor]:
    """Raw parameters for Gaussians at ``points`` (N,3) with RGB ``colors`` (N,3) in [0,1]
    and isotropic std ``scales`` (N,). Random rotations, constant opacity."""
    from omnire.gaussians import num_sh_bases, rgb_to_sh0

    N = points.shape[0]
    quats = torch.randn(N, 4, generator=generator, dtype=points.dtype)
    quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    return {
        "means": points.clone(),
        "quats": quats,
        "scales": torch.log(scales.clamp_min(1e-6))[:, None].repeat(1, 3),
        "opacities": torch.logit(torch.full((N,), opacity, dtype=points.dtype)),
        "sh0": rgb_to_sh0(colors),
        "shN": torch.zeros(N, num_sh_bases(sh_degree) - 1, 3, dtype=points.dtype),
    }
