"""Test harnesses that the suite and the robustness checks share: :mod:`.fuzz` (random damage to
one coder's input) and :mod:`.hostile` (crafted and random hostile ``.pgs`` files, each decoded
in a memory-capped child process). Nothing of the pipeline imports them."""
