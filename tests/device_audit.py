"""A stand-in accelerator for checking device-agnostic code on a CPU-only machine.

Code that runs on ``cuda`` fails where it mixes a tensor on the GPU with a CPU tensor of one or
more dimensions in one operation, turns a GPU tensor into a NumPy array, or draws GPU random
numbers from a CPU generator (the full list below).  Without a GPU those mistakes pass unnoticed, because every tensor
is on the CPU.  :class:`VirtualDevice` marks tensors instead: a tensor sent to ``VIRTUAL``
(``torch.device("cpu", 0)``, an ordinary CPU tensor) and everything computed from it counts as
"on the accelerator", its ``.device`` reads ``VIRTUAL``, and the three mistakes above raise
:class:`DeviceMixError` with the operation's name, as CUDA would.

Rules (PyTorch's own for CUDA tensors):
* an operation may mix accelerator tensors with CPU tensors of zero dimensions only, and joining
  (``torch.stack``, ``torch.cat``) mixes none;
* ``copy_``, ``.to`` and indexing move between devices, within CUDA's limits: CPU indices may index
  an accelerator tensor, not the other way round, and values assigned through advanced indexing
  (``t[idx] = v`` with a tensor or list in ``idx``) must be on ``t``'s device unless they have
  zero dimensions (a plain slice copies from anywhere);
* random numbers for an accelerator tensor (``torch.rand(..., device=)``, ``t.uniform_()``) come
  from a generator on the accelerator, not a CPU one;
* ``.cpu()``, ``.to("cpu")``, ``.item()``, ``.tolist()`` and ``float()`` leave the accelerator;
  ``.numpy()`` and ``np.asarray`` of an accelerator tensor fail.

A tensor is marked by a Python attribute, so the check follows every operation that goes through
``__torch_function__`` (all of ``torch``, ``torch.nn.functional`` and tensor methods).
"""

import threading

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

VIRTUAL = torch.device("cpu", 0)
_MARK = "_on_virtual_device"
_DEPTH_LOCK = threading.Lock()
_DEVICE_GET = torch.Tensor.device.__get__  # a fresh method-wrapper at each access: compare with ==


class DeviceMixError(RuntimeError):
    """What CUDA would have raised."""


def on_virtual(tensor: torch.Tensor) -> bool:
    """Whether ``tensor`` counts as on the accelerator; a ``torch.func`` wrapper (jacrev, vmap)
    counts as the tensor it wraps."""
    if hasattr(tensor, _MARK):
        return getattr(tensor, _MARK)
    if torch._C._functorch.is_functorch_wrapped_tensor(tensor):
        return on_virtual(torch._C._functorch.get_unwrapped(tensor))
    return False


def _mark(value, flag: bool) -> None:
    for leaf in tree_flatten(value)[0]:
        if isinstance(leaf, torch.Tensor):
            setattr(leaf, _MARK, flag)


def _target_device(func, args, kwargs):
    """The device an operation is asked to put its result on, or None."""
    if "device" in kwargs and kwargs["device"] is not None:
        return torch.device(kwargs["device"])
    if func in (torch.Tensor.to, torch.Tensor.type):
        for value in args[1:]:
            if isinstance(value, torch.Tensor):
                return VIRTUAL if on_virtual(value) else torch.device("cpu")
            if isinstance(value, torch.device):
                return value
            if isinstance(value, str):
                try:
                    return torch.device(value)
                except RuntimeError:
                    continue
    return None


_LEAVE = {torch.Tensor.cpu, torch.Tensor.item, torch.Tensor.tolist, torch.Tensor.__float__,
          torch.Tensor.__int__, torch.Tensor.__bool__, torch.Tensor.__index__}
_TO_NUMPY = {torch.Tensor.numpy, torch.Tensor.__array__}
_UNCHECKED = {torch.autograd.grad, torch.autograd.backward, torch.Tensor.backward}  # torch makes their seeds
_MOVE = {torch.Tensor.to, torch.Tensor.copy_, torch.Tensor.__getitem__, torch.Tensor.__setitem__,
         torch.Tensor.type}


_INDEXING = {torch.Tensor.__getitem__, torch.Tensor.__setitem__}
_JOIN = {torch.stack, torch.cat, torch.concat, torch.concatenate, torch.hstack, torch.vstack, torch.dstack}


def _check_indexing(name: str, args) -> None:
    """CUDA's indexing limits: no accelerator index into a CPU tensor; through an advanced index,
    no CPU values of one or more dimensions into an accelerator tensor."""
    indexed, index = args[0], args[1]
    index_leaves = tree_flatten(index if isinstance(index, tuple) else (index,))[0]
    index_tensors = [leaf for leaf in index_leaves if isinstance(leaf, torch.Tensor)]
    if not on_virtual(indexed) and any(on_virtual(t) and t.dim() > 0 for t in index_tensors):
        raise DeviceMixError(f"{name}: an index on the accelerator into a CPU tensor {tuple(indexed.shape)}")
    advanced = bool(index_tensors) or isinstance(index, list) or any(isinstance(leaf, list) for leaf in
                                                                      (index if isinstance(index, tuple) else ()))
    values = args[2] if len(args) > 2 else None
    if (on_virtual(indexed) and advanced and isinstance(values, torch.Tensor) and not on_virtual(values)
            and values.dim() > 0):
        raise DeviceMixError(f"{name}: CPU values {tuple(values.shape)} assigned through an advanced index into an "
                             f"accelerator tensor (move them to its device first)")


def _marking(transform):
    """``torch.func`` transform whose results count as on the accelerator when an input does (the
    transform unwraps its results out of this mode's sight)."""

    def wrapped_transform(*transform_args, **transform_kwargs):
        if transform.__name__ == "jvp":  # jvp(f, primals, tangents) evaluates at once
            result = transform(*transform_args, **transform_kwargs)
            inputs = transform_args[1:]
            _mark(result, any(on_virtual(t) for t in tree_flatten(inputs)[0] if isinstance(t, torch.Tensor)))
            return result
        function = transform(*transform_args, **transform_kwargs)

        def evaluate(*args, **kwargs):
            result = function(*args, **kwargs)
            _mark(result, any(on_virtual(t) for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)))
            return result

        return evaluate

    return wrapped_transform


class VirtualDevice(TorchFunctionMode):
    """``with VirtualDevice(): ...`` runs code with tensors on ``VIRTUAL`` checked as if on a GPU.

    ``Module.to`` replaces a parameter's data behind ``param.data = ...``, ``Parameter(data)``
    wraps a tensor in a new object and ``torch.func`` transforms unwrap their results, all out of
    this mode's sight, so while the mode is on those carry the mark over.  A mode holds for its
    own thread only, so a thread started inside the block runs under the same mode.
    """

    def __init__(self):
        super().__init__()
        self._local = threading.local()
        self._patches = None

    def _patch(self):
        mode = self
        module_to, parameter_new, thread_run = torch.nn.Module.to, torch.nn.Parameter.__new__, threading.Thread.run
        transforms = {name: getattr(torch.func, name) for name in ("jacrev", "jacfwd", "jvp", "vmap")}

        def to(module, *args, **kwargs):
            mode._local.inside_module_to = True
            try:
                result = module_to(module, *args, **kwargs)
            finally:
                mode._local.inside_module_to = False
            target = _target_device(torch.Tensor.to, (None, *args), kwargs)
            if target is not None:
                for tensor in list(module.parameters()) + list(module.buffers()):
                    setattr(tensor, _MARK, target == VIRTUAL)
            return result

        def new_parameter(cls, data=None, requires_grad=True):
            parameter = parameter_new(cls, data, requires_grad)
            setattr(parameter, _MARK, data is not None and on_virtual(data))
            return parameter

        def run(thread):
            with mode:
                thread_run(thread)

        torch.nn.Module.to, torch.nn.Parameter.__new__, threading.Thread.run = to, new_parameter, run
        for name, transform in transforms.items():
            setattr(torch.func, name, _marking(transform))
        self._patches = (module_to, parameter_new, thread_run, transforms)

    def _unpatch(self):
        module_to, parameter_new, thread_run, transforms = self._patches
        torch.nn.Module.to, torch.nn.Parameter.__new__, threading.Thread.run = module_to, parameter_new, thread_run
        for name, transform in transforms.items():
            setattr(torch.func, name, transform)
        self._patches = None

    def __enter__(self):
        with _DEPTH_LOCK:
            if self._patches is None:
                self._patch()
                self._depth = 0
            self._depth += 1
        return super().__enter__()

    def __exit__(self, *exc):
        with _DEPTH_LOCK:
            self._depth -= 1
            if self._depth == 0:
                self._unpatch()
        return super().__exit__(*exc)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if getattr(self._local, "inside_module_to", False):
            return func(*args, **kwargs)
        if func == _DEVICE_GET:
            return VIRTUAL if on_virtual(args[0]) else torch.device("cpu")
        tensors = [leaf for leaf in tree_flatten((args, kwargs))[0] if isinstance(leaf, torch.Tensor)]
        virtual = [t for t in tensors if on_virtual(t)]
        name = getattr(func, "__qualname__", getattr(func, "__name__", repr(func)))
        if func in _TO_NUMPY and virtual:
            raise DeviceMixError(f"{name}: a tensor on the accelerator cannot become a NumPy array (call .cpu() first)")
        target = _target_device(func, args, kwargs)
        generator = kwargs.get("generator")
        filled = args[0] if args and isinstance(args[0], torch.Tensor) else None  # t.uniform_(generator=...)
        if (target == VIRTUAL or (filled is not None and on_virtual(filled))) and isinstance(
                generator, torch.Generator) and generator.device.type == "cpu":
            raise DeviceMixError(f"{name}: random numbers on the accelerator from a CPU generator")
        if func in _INDEXING:
            _check_indexing(name, args)
        if func in _JOIN and virtual and len(virtual) < len(tensors):
            raise DeviceMixError(f"{name}: joins accelerator and CPU tensors (CUDA joins only tensors on one device)")
        if virtual and func not in _MOVE and func not in _LEAVE and func not in _UNCHECKED:
            cpu = [t for t in tensors if not on_virtual(t) and t.dim() > 0]
            if cpu:
                raise DeviceMixError(
                    f"{name}: accelerator tensor(s) {[tuple(t.shape) for t in virtual]} mixed with CPU "
                    f"tensor(s) {[tuple(t.shape) for t in cpu]}")
        result = func(*args, **kwargs)
        if func is torch.Tensor.cpu:
            target = torch.device("cpu")
        if result is (args[0] if args else None) and target is not None and on_virtual(result) != (target == VIRTUAL):
            result = result.view_as(result)  # a move that is a no-op on the CPU: a new object to mark
        if func in _LEAVE or (target is not None and target != VIRTUAL):
            _mark(result, False)
        elif target == VIRTUAL:
            _mark(result, True)
        elif func is torch.Tensor.__setitem__ or func is torch.Tensor.copy_:
            pass  # the destination keeps its device
        elif func is torch.Tensor.__getitem__:
            _mark(result, on_virtual(args[0]))
        elif virtual:
            _mark(result, True)
        return result
