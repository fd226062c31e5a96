"""Attribute encodings (binary, log, signed log, rotation) and their robust inverses.

Every function works on numpy arrays and on torch tensors alike (same type out as in),
vectorised over any leading shape, so the tokenizer (numpy) and guidance (torch, with
gradients through the continuous decoders) share one definition.

Decoders never fail on model output: binary values are clipped to [0, 1] and rounded, log
values are clipped to a finite range, rotations are projected onto SO(3).
"""

from __future__ import annotations

import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.tokens.schema import LOG_OFFSET, Attribute, Encoding

#: Log-space values beyond this are clipped before exponentiation (exp(30) ~ 1e13).
_LOG_CLIP = 30.0


def _is_torch(x) -> bool:
    return isinstance(x, torch.Tensor)


def encode_binary(values, bits: int, offset: int = 0):
    """Integers (...) -> bits (..., bits), most significant bit first, of ``values + offset``.

    Raises ValueError naming the first value outside ``[-offset, 2**bits - 1 - offset]``.
    """
    if _is_torch(values):
        v = values.long() + offset
        if v.numel() and (int(v.min()) < 0 or int(v.max()) > 2**bits - 1):
            bad = int((v[(v < 0) | (v > 2**bits - 1)][0]) - offset)
            raise TTError(
                f"value {bad} does not fit {bits} bits with offset {offset}: valid {-offset}..{2**bits - 1 - offset}"
            )
        shifts = torch.arange(bits - 1, -1, -1, device=v.device)
        return ((v.unsqueeze(-1) >> shifts) & 1).float()
    v = np.asarray(values).astype(np.int64) + offset
    if v.size and (v.min() < 0 or v.max() > 2**bits - 1):
        bad = int(v[(v < 0) | (v > 2**bits - 1)][0]) - offset
        raise TTError(
            f"value {bad} does not fit {bits} bits with offset {offset}: valid {-offset}..{2**bits - 1 - offset}"
        )
    shifts = np.arange(bits - 1, -1, -1)
    return ((v[..., None] >> shifts) & 1).astype(np.float64)


def decode_binary(x, offset: int = 0):
    """Bits (..., bits) -> integers (...): clip to [0, 1], round (0.5 up), read MSB first,
    subtract offset."""
    bits = x.shape[-1]
    if _is_torch(x):
        b = (x >= 0.5).long()  # clip to [0, 1] and round; NaN compares False -> 0
        weights = 2 ** torch.arange(bits - 1, -1, -1, device=x.device)
        return (b * weights).sum(-1) - offset
    x = np.asarray(x, dtype=np.float64)
    b = (x >= 0.5).astype(np.int64)  # clip to [0, 1] and round; NaN compares False -> 0
    weights = 2 ** np.arange(bits - 1, -1, -1)
    return (b * weights).sum(-1) - offset


def encode_log(x, offset: float = LOG_OFFSET):
    """``log(x + offset)`` of non-negative values (negative inputs are clipped to 0)."""
    if _is_torch(x):
        return torch.log(x.clamp(min=0.0) + offset)
    return np.log(np.maximum(x, 0.0) + offset)


def decode_log(y, offset: float = LOG_OFFSET):
    """Inverse of `encode_log`, clipped at 0 (a decoded mass or gain is never negative)."""
    if _is_torch(y):
        return (torch.exp(torch.nan_to_num(y, nan=-_LOG_CLIP).clamp(-_LOG_CLIP, _LOG_CLIP)) - offset).clamp(min=0.0)
    y = np.clip(np.where(np.isnan(y), -_LOG_CLIP, y), -_LOG_CLIP, _LOG_CLIP)
    return np.maximum(np.exp(y) - offset, 0.0)


def encode_signed_log(x, offset: float = LOG_OFFSET):
    """Values (..., d) -> (..., 2d) as interleaved pairs ``[log(|x| + offset), x < 0]``."""
    if _is_torch(x):
        pair = torch.stack([torch.log(x.abs() + offset), (x < 0).to(x.dtype)], dim=-1)
        return pair.reshape(*x.shape[:-1], -1)
    x = np.asarray(x, dtype=np.float64)
    pair = np.stack([np.log(np.abs(x) + offset), (x < 0).astype(np.float64)], axis=-1)
    return pair.reshape(*x.shape[:-1], -1)


def decode_signed_log(y, offset: float = LOG_OFFSET):
    """Inverse of `encode_signed_log`: (..., 2d) -> (..., d); a sign value >= 0.5 means negative."""
    if _is_torch(y):
        y = torch.nan_to_num(y, nan=0.0)
        pair = y.reshape(*y.shape[:-1], y.shape[-1] // 2, 2)
        mag = (torch.exp(pair[..., 0].clamp(-_LOG_CLIP, _LOG_CLIP)) - offset).clamp(min=0.0)
        return torch.where(pair[..., 1] >= 0.5, -mag, mag)
    y = np.nan_to_num(np.asarray(y, dtype=np.float64), nan=0.0)
    pair = y.reshape(*y.shape[:-1], y.shape[-1] // 2, 2)
    mag = np.maximum(np.exp(np.clip(pair[..., 0], -_LOG_CLIP, _LOG_CLIP)) - offset, 0.0)
    return np.where(pair[..., 1] >= 0.5, -mag, mag)


def project_rotation(x):
    """Nine values (..., 9) -> the nearest rotation matrix (..., 3, 3) (SVD, det +1).

    Degenerate input (all zeros, NaN) decodes to the identity.
    """
    if _is_torch(x):
        m = torch.nan_to_num(x, nan=0.0).reshape(*x.shape[:-1], 3, 3)
        bad = m.abs().sum((-1, -2)) < 1e-9
        m = torch.where(bad[..., None, None], torch.eye(3, dtype=m.dtype, device=m.device).expand_as(m), m)
        u, _, vh = torch.linalg.svd(m)
        det = torch.linalg.det(u @ vh)
        d = torch.ones_like(m[..., 0])
        d[..., 2] = torch.sign(det) + (det == 0).to(det.dtype)
        return (u * d[..., None, :]) @ vh
    m = np.nan_to_num(np.asarray(x, dtype=np.float64), nan=0.0).reshape(*np.shape(x)[:-1], 3, 3)
    bad = np.abs(m).sum((-1, -2)) < 1e-9
    m = np.where(bad[..., None, None], np.eye(3), m)
    u, _, vh = np.linalg.svd(m)
    det = np.linalg.det(u @ vh)
    d = np.ones(m.shape[:-1])
    d[..., 2] = np.where(det < 0, -1.0, 1.0)
    return (u * d[..., None, :]) @ vh


def encode_attribute(attr: Attribute, raw):
    """Raw values -> encoded values of width ``attr.width``.

    raw: (..., attr.dim) for every encoding except BINARY ((...) integers) and ROTATION
    ((..., 3, 3) matrices or (..., 9)).
    """
    enc = attr.encoding
    if enc is Encoding.BINARY:
        return encode_binary(raw, attr.bits, attr.offset)
    if enc is Encoding.LOG:
        return encode_log(raw, attr.log_offset)
    if enc is Encoding.SIGNED_LOG:
        return encode_signed_log(raw, attr.log_offset)
    if enc is Encoding.ROTATION:
        return raw.reshape(*raw.shape[:-2], 9) if tuple(raw.shape[-2:]) == (3, 3) else raw
    return raw


def decode_attribute(attr: Attribute, values):
    """Encoded values (..., attr.width) -> raw values (robust; see module docstring).

    Returns (...) integers for BINARY, (..., 3, 3) for ROTATION, else (..., attr.dim).
    """
    enc = attr.encoding
    if enc is Encoding.BINARY:
        return decode_binary(values, attr.offset)
    if enc is Encoding.LOG:
        return decode_log(values, attr.log_offset)
    if enc is Encoding.SIGNED_LOG:
        return decode_signed_log(values, attr.log_offset)
    if enc is Encoding.ROTATION:
        return project_rotation(values)
    if _is_torch(values):
        return torch.nan_to_num(values, nan=0.0)
    x = np.asarray(values, dtype=np.float64)
    return x if np.isfinite(x).all() else np.nan_to_num(x, nan=0.0)
