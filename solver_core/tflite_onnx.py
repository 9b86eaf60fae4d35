"""Convert the small float TFLite vision models we use (BlazePose GHUM) to ONNX.

Why our own converter: ``tflite2onnx`` 0.4.1 fails on both BlazePose models (a
PAD constant shared between operators; the detector's DENSIFY op) and ``tf2onnx``
needs a full TensorFlow.  The two models use a dozen builtin operators, all with
static shapes, so a direct translation is short:

* constants (float16 weights, sparse weights) are materialised in numpy at
  conversion time -- DEQUANTIZE and DENSIFY of constants never reach the graph;
* 4-D activations live in ONNX's NCHW layout; TFLite's NHWC semantics are kept by
  remapping axes/paddings and by transposing back to NHWC only where the layout is
  observable (RESHAPE of a 4-D tensor, graph outputs);
* outputs the caller does not want (the segmentation mask) are dropped, and every
  operator that only fed them is pruned.

Facts used (TFLite flatbuffer schema, public): Padding SAME=0 / VALID=1; fused
activation NONE=0, RELU=1, RELU_N1_TO_1=2, RELU6=3; conv weights are
``[O, KH, KW, I]``, depthwise weights ``[1, KH, KW, C*M]``; TF's DepthToSpace is
ONNX's ``DCR`` mode; ``half_pixel_centers`` bilinear resize is ONNX ``half_pixel``.

Requires the ``tflite`` (flatbuffer schema) and ``onnx`` packages, only when
converting; inference needs only onnxruntime.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


class TfliteConversionError(ValueError):
    """The TFLite file uses something this converter does not translate."""


_TFLITE_DTYPES = {0: np.float32, 1: np.float16, 2: np.int32, 3: np.uint8, 4: np.int64, 9: np.int8}
_SAME, _VALID = 0, 1


@dataclass
class _Value:
    """A tensor in the ONNX graph being built: its ONNX name, TFLite (NHWC) shape, layout."""

    name: str
    shape: tuple[int, ...]  # TFLite shape (NHWC for 4-D)
    nchw: bool  # True when the ONNX tensor holds the NHWC tensor transposed to NCHW


def _enum_names(enum_cls) -> dict[int, str]:
    return {v: k for k, v in vars(enum_cls).items() if not k.startswith("_") and isinstance(v, int)}


def _index_vector(tflite, dm, which: str) -> np.ndarray:
    """Read a SparseIndexVector union (segments or indices) of a DimensionMetadata."""
    kind = getattr(dm, f"Array{which}Type")()
    table = getattr(dm, f"Array{which}")()
    vec_cls = {1: tflite.Int32Vector, 2: tflite.Uint16Vector, 3: tflite.Uint8Vector}.get(kind)
    if vec_cls is None or table is None:
        raise TfliteConversionError(f"sparse tensor has an unsupported index vector type {kind}")
    vec = vec_cls()
    vec.Init(table.Bytes, table.Pos)
    return vec.ValuesAsNumpy().astype(np.int64)


def densify(values: np.ndarray, shape: tuple[int, ...], sparsity, tflite) -> np.ndarray:
    """Expand a TFLite sparse constant (TACO-style dimension metadata) to a dense array.

    values: (nnz,) stored values in traversal order; shape: dense shape.
    The dimension metadata lists, in traversal order, each (possibly blocked)
    dimension as DENSE (a dense size) or SPARSE_CSR (segments + indices).
    """
    traversal = list(sparsity.TraversalOrderAsNumpy()) if sparsity.TraversalOrderLength() else list(range(len(shape)))
    block_map = list(sparsity.BlockMapAsNumpy()) if sparsity.BlockMapLength() else []
    levels = []
    for d in range(sparsity.DimMetadataLength()):
        dm = sparsity.DimMetadata(d)
        if dm.Format() == 0:
            levels.append(("dense", int(dm.DenseSize()), None, None))
        else:
            levels.append(("csr", 0, _index_vector(tflite, dm, "Segments"), _index_vector(tflite, dm, "Indices")))
    n_dims = len(shape)
    block_sizes = {}
    for k, orig_dim in enumerate(block_map):
        level = levels[traversal.index(n_dims + k)]
        block_sizes[orig_dim] = level[1]  # block dimensions are always stored dense
    dense = np.zeros(shape, dtype=values.dtype)
    coords = [0] * len(levels)

    def visit(level: int, pos: int) -> None:
        kind, size, segments, indices = levels[level]
        last = level == len(levels) - 1
        if kind == "dense":
            children = ((i, pos * size + i) for i in range(size))
        else:
            children = ((int(indices[j]), j) for j in range(int(segments[pos]), int(segments[pos + 1])))
        for coord, child_pos in children:
            coords[level] = coord
            if last:
                index = [0] * n_dims
                for lvl, c in enumerate(coords):
                    dim = traversal[lvl]
                    if dim < n_dims:
                        index[dim] += c * block_sizes.get(dim, 1)
                    else:
                        index[block_map[dim - n_dims]] += c
                dense[tuple(index)] = values[child_pos]
            else:
                visit(level + 1, child_pos)

    visit(0, 0)
    return dense


class _Converter:
    def __init__(self, model_bytes: bytes, keep_outputs: list[str] | None):
        import tflite  # schema package; only needed while converting

        self.tflite = tflite
        self.model = tflite.Model.GetRootAsModel(model_bytes, 0)
        if self.model.SubgraphsLength() != 1:
            raise TfliteConversionError("only single-subgraph TFLite models are supported")
        self.graph = self.model.Subgraphs(0)
        self.op_names = _enum_names(tflite.BuiltinOperator)
        self.keep_outputs = keep_outputs
        self.nodes: list = []
        self.initializers: list = []
        self.values: dict[int, _Value] = {}
        self.constants: dict[int, np.ndarray] = {}
        self._counter = 0

    # -- helpers -----------------------------------------------------------
    def fresh(self, base: str) -> str:
        self._counter += 1
        return f"{base}_{self._counter}"

    def tensor_shape(self, idx: int) -> tuple[int, ...]:
        return tuple(int(s) for s in self.graph.Tensors(idx).ShapeAsNumpy())

    def constant(self, idx: int) -> np.ndarray | None:
        """The numpy value of a constant tensor (weights), or None for activations."""
        if idx in self.constants:
            return self.constants[idx]
        tensor = self.graph.Tensors(idx)
        buffer = self.model.Buffers(tensor.Buffer())
        if buffer is None or buffer.DataLength() == 0:
            return None
        dtype = _TFLITE_DTYPES.get(tensor.Type())
        if dtype is None:
            raise TfliteConversionError(f"tensor {tensor.Name()!r} has unsupported type {tensor.Type()}")
        raw = np.frombuffer(buffer.DataAsNumpy().tobytes(), dtype=dtype)
        shape = self.tensor_shape(idx)
        if tensor.Sparsity() is not None:
            value = densify(raw, shape, tensor.Sparsity(), self.tflite)
        else:
            value = raw.reshape(shape) if shape else raw.reshape(())
        if tensor.Quantization() is not None and tensor.Quantization().ScaleLength() and dtype in (np.uint8, np.int8):
            raise TfliteConversionError("integer-quantised tensors are not supported")
        self.constants[idx] = value
        return value

    def add_init(self, array: np.ndarray, base: str) -> str:
        from onnx import numpy_helper

        name = self.fresh(base)
        self.initializers.append(numpy_helper.from_array(np.ascontiguousarray(array), name))
        return name

    def node(self, op: str, inputs: list[str], base: str, **attrs) -> str:
        from onnx import helper

        out = self.fresh(base)
        self.nodes.append(helper.make_node(op, inputs, [out], name=out, **attrs))
        return out

    def as_layout(self, value: _Value, nchw: bool) -> str:
        if value.nchw == nchw or len(value.shape) != 4:
            return value.name
        perm = [0, 3, 1, 2] if nchw else [0, 2, 3, 1]
        return self.node("Transpose", [value.name], "transpose", perm=perm)

    def activation_input(self, idx: int) -> _Value:
        if idx in self.values:
            return self.values[idx]
        const = self.constant(idx)
        if const is None:
            raise TfliteConversionError(f"tensor {self.graph.Tensors(idx).Name()!r} used before it is produced")
        # A constant operand of an elementwise op: give it the NCHW broadcast shape.
        arr = const.astype(np.float32) if const.dtype == np.float16 else const
        if arr.ndim == 4:
            arr = arr.transpose(0, 3, 1, 2)
            return _Value(self.add_init(arr, "const"), tuple(const.shape), True)
        if arr.ndim == 1:
            arr = arr.reshape(1, -1, 1, 1)
            return _Value(self.add_init(arr, "const"), (1, 1, 1, const.shape[0]), True)
        return _Value(self.add_init(arr, "const"), tuple(const.shape), False)

    def fused(self, name: str, act: int) -> str:
        if act == 0:
            return name
        if act == 1:
            return self.node("Relu", [name], "relu")
        if act == 3:
            lo = self.add_init(np.array(0.0, np.float32), "lo")
            hi = self.add_init(np.array(6.0, np.float32), "hi")
            return self.node("Clip", [name, lo, hi], "relu6")
        if act == 2:
            lo = self.add_init(np.array(-1.0, np.float32), "lo")
            hi = self.add_init(np.array(1.0, np.float32), "hi")
            return self.node("Clip", [name, lo, hi], "relu_n1_1")
        raise TfliteConversionError(f"unsupported fused activation {act}")

    def options(self, op, cls_name: str):
        table = op.BuiltinOptions()
        opts = getattr(self.tflite, cls_name)()
        opts.Init(table.Bytes, table.Pos)
        return opts

    @staticmethod
    def same_pads(in_hw, kernel_hw, stride_hw, dilation_hw) -> list[int]:
        """TF 'SAME' padding: extra padding goes after (bottom/right). Returns [top, left, bottom, right]."""
        begins, ends = [], []
        for size, k, s, d in zip(in_hw, kernel_hw, stride_hw, dilation_hw):
            out = -(-size // s)
            eff_k = (k - 1) * d + 1
            total = max((out - 1) * s + eff_k - size, 0)
            begins.append(total // 2)
            ends.append(total - total // 2)
        return begins + ends

    # -- operators ---------------------------------------------------------
    def convert_op(self, op) -> None:
        code = self.model.OperatorCodes(op.OpcodeIndex())
        name = self.op_names.get(max(code.BuiltinCode(), code.DeprecatedBuiltinCode()), "CUSTOM")
        ins = [int(i) for i in op.InputsAsNumpy()]
        outs = [int(i) for i in op.OutputsAsNumpy()]
        out_shape = self.tensor_shape(outs[0])

        if name in ("DEQUANTIZE", "DENSIFY"):
            const = self.constant(ins[0])
            if const is None:
                raise TfliteConversionError(f"{name} of a non-constant tensor is not supported")
            self.constants[outs[0]] = const.astype(np.float32) if name == "DEQUANTIZE" else const
            return

        if name in ("CONV_2D", "DEPTHWISE_CONV_2D"):
            x = self.activation_input(ins[0])
            weight = self.constant(ins[1])
            bias = self.constant(ins[2]) if len(ins) > 2 and ins[2] >= 0 else None
            if weight is None:
                raise TfliteConversionError(f"{name} with non-constant weights")
            weight = weight.astype(np.float32)
            depthwise = name == "DEPTHWISE_CONV_2D"
            opts = self.options(op, "DepthwiseConv2DOptions" if depthwise else "Conv2DOptions")
            if depthwise:
                channels = x.shape[3]
                w = weight.transpose(3, 0, 1, 2)  # [C*M, 1, KH, KW]
                group = channels
            else:
                w = weight.transpose(0, 3, 1, 2)  # [O, I, KH, KW]
                group = 1
            kernel = w.shape[2:]
            strides = [opts.StrideH(), opts.StrideW()]
            dilations = [opts.DilationHFactor() or 1, opts.DilationWFactor() or 1]
            if opts.Padding() == _SAME:
                pads = self.same_pads(x.shape[1:3], kernel, strides, dilations)
            else:
                pads = [0, 0, 0, 0]
            inputs = [self.as_layout(x, True), self.add_init(w, "w")]
            if bias is not None:
                inputs.append(self.add_init(bias.astype(np.float32), "b"))
            y = self.node("Conv", inputs, "conv", kernel_shape=list(kernel), strides=strides,
                          dilations=dilations, pads=pads, group=group)
            y = self.fused(y, opts.FusedActivationFunction())
            self.values[outs[0]] = _Value(y, out_shape, True)
            return

        if name in ("ADD", "MUL", "SUB"):
            a, b = self.activation_input(ins[0]), self.activation_input(ins[1])
            opts = self.options(op, {"ADD": "AddOptions", "MUL": "MulOptions", "SUB": "SubOptions"}[name])
            nchw = len(out_shape) == 4
            y = self.node({"ADD": "Add", "MUL": "Mul", "SUB": "Sub"}[name],
                          [self.as_layout(a, nchw), self.as_layout(b, nchw)], name.lower())
            y = self.fused(y, opts.FusedActivationFunction())
            self.values[outs[0]] = _Value(y, out_shape, nchw)
            return

        if name == "PAD":
            x = self.activation_input(ins[0])
            paddings = self.constant(ins[1])
            if paddings is None:
                raise TfliteConversionError("PAD with non-constant paddings")
            paddings = np.asarray(paddings, np.int64).reshape(-1, 2)
            if len(x.shape) == 4:
                order = [0, 3, 1, 2]
                paddings = paddings[order]
            pads = np.concatenate([paddings[:, 0], paddings[:, 1]]).astype(np.int64)
            y = self.node("Pad", [self.as_layout(x, True), self.add_init(pads, "pads")], "pad", mode="constant")
            self.values[outs[0]] = _Value(y, out_shape, len(x.shape) == 4)
            return

        if name == "RESHAPE":
            x = self.activation_input(ins[0])
            shape = np.asarray(out_shape, np.int64)
            y = self.node("Reshape", [self.as_layout(x, False), self.add_init(shape, "shape")], "reshape")
            value = _Value(y, out_shape, False)
            if len(out_shape) == 4:  # keep 4-D activations in NCHW
                value = _Value(self.as_layout(value, True), out_shape, True)
            self.values[outs[0]] = value
            return

        if name == "DEPTH_TO_SPACE":
            x = self.activation_input(ins[0])
            opts = self.options(op, "DepthToSpaceOptions")
            y = self.node("DepthToSpace", [self.as_layout(x, True)], "d2s", blocksize=opts.BlockSize(), mode="DCR")
            self.values[outs[0]] = _Value(y, out_shape, True)
            return

        if name == "RESIZE_BILINEAR":
            x = self.activation_input(ins[0])
            opts = self.options(op, "ResizeBilinearOptions")
            if opts.AlignCorners():
                mode = "align_corners"
            elif opts.HalfPixelCenters():
                mode = "half_pixel"
            else:
                mode = "asymmetric"
            sizes = np.array([out_shape[0], out_shape[3], out_shape[1], out_shape[2]], np.int64)
            y = self.node("Resize", [self.as_layout(x, True), "", "", self.add_init(sizes, "sizes")], "resize",
                          mode="linear", coordinate_transformation_mode=mode)
            self.values[outs[0]] = _Value(y, out_shape, True)
            return

        if name in ("MAX_POOL_2D", "AVERAGE_POOL_2D"):
            x = self.activation_input(ins[0])
            opts = self.options(op, "Pool2DOptions")
            kernel = [opts.FilterHeight(), opts.FilterWidth()]
            strides = [opts.StrideH(), opts.StrideW()]
            pads = self.same_pads(x.shape[1:3], kernel, strides, [1, 1]) if opts.Padding() == _SAME else [0, 0, 0, 0]
            onnx_op = "MaxPool" if name == "MAX_POOL_2D" else "AveragePool"
            extra = {"count_include_pad": 0} if onnx_op == "AveragePool" else {}
            y = self.node(onnx_op, [self.as_layout(x, True)], "pool", kernel_shape=kernel, strides=strides,
                          pads=pads, **extra)
            y = self.fused(y, opts.FusedActivationFunction())
            self.values[outs[0]] = _Value(y, out_shape, True)
            return

        if name == "CONCATENATION":
            values = [self.activation_input(i) for i in ins]
            opts = self.options(op, "ConcatenationOptions")
            axis = opts.Axis() % len(out_shape)
            nchw = len(out_shape) == 4
            if nchw:
                axis = [0, 2, 3, 1][axis]
            y = self.node("Concat", [self.as_layout(v, nchw) for v in values], "concat", axis=axis)
            y = self.fused(y, opts.FusedActivationFunction())
            self.values[outs[0]] = _Value(y, out_shape, nchw)
            return

        if name in ("LOGISTIC", "RELU", "RELU6", "TANH"):
            x = self.activation_input(ins[0])
            if name == "RELU6":
                y = self.fused(x.name, 3)
            else:
                y = self.node({"LOGISTIC": "Sigmoid", "RELU": "Relu", "TANH": "Tanh"}[name], [x.name], name.lower())
            self.values[outs[0]] = _Value(y, out_shape, x.nchw)
            return

        raise TfliteConversionError(f"TFLite operator {name} is not supported by this converter")

    # -- graph -------------------------------------------------------------
    def needed_ops(self, output_ids: list[int]) -> list[int]:
        """Indices of operators that (transitively) feed the kept outputs, in graph order."""
        producer = {}
        for i in range(self.graph.OperatorsLength()):
            for t in self.graph.Operators(i).OutputsAsNumpy():
                producer[int(t)] = i
        needed, stack = set(), list(output_ids)
        while stack:
            t = stack.pop()
            i = producer.get(t)
            if i is None or i in needed:
                continue
            needed.add(i)
            stack.extend(int(x) for x in self.graph.Operators(i).InputsAsNumpy() if x >= 0)
        return sorted(needed)

    def run(self, graph_name: str):
        from onnx import TensorProto, helper

        inputs = []
        for i in range(self.graph.InputsLength()):
            idx = int(self.graph.Inputs(i))
            tensor = self.graph.Tensors(idx)
            shape = self.tensor_shape(idx)
            name = tensor.Name().decode()
            inputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(shape)))
            self.values[idx] = _Value(name, shape, False)

        output_ids, output_names = [], []
        for i in range(self.graph.OutputsLength()):
            idx = int(self.graph.Outputs(i))
            name = self.graph.Tensors(idx).Name().decode()
            if self.keep_outputs is None or name in self.keep_outputs:
                output_ids.append(idx)
                output_names.append(name)
        if self.keep_outputs is not None and set(self.keep_outputs) - set(output_names):
            raise TfliteConversionError(f"model has no outputs named {sorted(set(self.keep_outputs) - set(output_names))}")

        for i in self.needed_ops(output_ids):
            self.convert_op(self.graph.Operators(i))

        outputs = []
        for idx, name in zip(output_ids, output_names):
            value = self.values[idx]
            src = self.as_layout(value, False)
            self.nodes.append(helper.make_node("Identity", [src], [name], name=f"out_{name}"))
            outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(value.shape)))

        graph = helper.make_graph(self.nodes, graph_name, inputs, outputs, self.initializers)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)],
                                  producer_name="uuomocap.tflite_onnx")
        model.ir_version = 8
        return model


def convert_tflite_to_onnx(tflite_path: str | Path, onnx_path: str | Path,
                           keep_outputs: list[str] | None = None) -> Path:
    """Translate a float TFLite model to an ONNX file; ``keep_outputs`` prunes the rest.

    Raises TfliteConversionError naming the first unsupported feature.
    """
    import onnx

    tflite_path, onnx_path = Path(tflite_path), Path(onnx_path)
    model = _Converter(tflite_path.read_bytes(), keep_outputs).run(tflite_path.stem)
    onnx.checker.check_model(model)
    tmp = onnx_path.with_suffix(onnx_path.suffix + ".tmp")
    onnx.save(model, str(tmp))
    tmp.replace(onnx_path)
    return onnx_path
