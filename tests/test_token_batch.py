"""`tt.tokens.batch.TokenBatch`, the one token container: numpy (tokenizer, store, files)
and torch (the DiT), schema types checked against the schema, other types for shapes; and
the one `Role` / `PAD_VALUE` every layer reads."""

import numpy as np
import pytest
import torch

from tt.tokens.batch import TokenBatch
from tt.tokens.schema import SCHEMA, STEP_ROLES, Role


def _toy(n: int = 3, length: int = 4) -> TokenBatch:
    g = torch.Generator().manual_seed(0)
    return TokenBatch(
        {"body": torch.randn(n, length, 5, generator=g), "link": torch.randn(n, 2, SCHEMA["link"].width, generator=g)},
        {
            "body": torch.randint(0, 4, (n, length, 1), generator=g),
            "link": torch.randint(0, 4, (n, 2, len(SCHEMA["link"].ids)), generator=g),
        },
        {"body": torch.rand(n, length, generator=g) > 0.3, "link": torch.ones(n, 2, dtype=torch.bool)},
    )


def test_shapes_are_checked_for_schema_and_other_types():
    b = _toy()
    assert b.types == ("link", "body")  # schema types first, in schema order, then the others
    with pytest.raises(ValueError, match=r"mask\['body'\] has shape"):
        TokenBatch({"body": b.values["body"]}, {"body": b.ids["body"]}, {"body": b.mask["body"][:, :-1]})
    with pytest.raises(ValueError, match=r"ids\['body'\] has shape"):
        TokenBatch({"body": b.values["body"]}, {"body": b.ids["body"][:, :, 0]}, {"body": b.mask["body"]})
    with pytest.raises(ValueError, match=r"values\['link'\] has width 3"):
        TokenBatch({"link": torch.zeros(1, 2, 3)}, {"link": b.ids["link"][:1]}, {"link": b.mask["link"][:1]})


def test_torch_and_numpy_operations_agree():
    b = _toy()
    c = b.clone()
    c.values["body"][0] += 1.0
    assert not torch.equal(c.values["body"], b.values["body"])  # no shared memory
    both = TokenBatch.concatenate([b, c])
    assert both.device == torch.device("cpu") and len(both) == 6
    for n in b.types:
        assert torch.equal(both.values[n], torch.cat([b.values[n], c.values[n]]))
    assert both.ids["body"].dtype == torch.int64 and b.to("cpu").values["body"].dtype == torch.float32
    keep = torch.tensor([True, False, True])
    sel = b.select(keep)
    assert torch.equal(sel.mask["body"], b.mask["body"][keep])
    # numpy batches of different lengths are padded to the longest; the torch result matches.
    short = b.select(slice(0, 1)).to_numpy()
    short = TokenBatch(
        {"body": short.values["body"][:, :2]}, {"body": short.ids["body"][:, :2]}, {"body": short.mask["body"][:, :2]}
    )
    padded = TokenBatch.concatenate([short, b.subset(["body"]).to_numpy()])
    assert padded.values["body"].shape == (4, 4, 5) and not padded.mask["body"][0, 2:].any()
    np.testing.assert_array_equal(padded.values["body"][1:], b.values["body"].numpy())


def test_one_role_and_pad_value():
    import tt.dit.layout as layout

    assert layout.Role is Role and layout.STEP_ROLES is STEP_ROLES
    assert "PAD_VALUE" not in vars(layout)  # one definition, in tt.tokens.schema
    roles = layout.schema_roles()
    assert roles["control"] is Role.ACTION and roles["target_pose"] is Role.CONDITION
    assert roles["link"] is Role.EMBODIMENT and roles["dyna_joint_obs"] is Role.DYNAMICS
    assert {t.role for t in SCHEMA.types} == set(Role)
    spec = layout.layout_from_schema({"link": 3, "control": 2, "target_pose": 1})
    assert [s.role for s in spec.specs] == [Role.EMBODIMENT, Role.ACTION, Role.CONDITION]
