"""Model-vs-recording diagnosis: locate the residual, name the missing physics, refit it.

Parts: :mod:`.simulation` (the estimator's model for N candidates), :mod:`.effects`
(the library of candidate extensions), :mod:`.refit` (joint least-squares),
:mod:`.locate` (where the residual concentrates), :mod:`.signatures` (evidence read from
the recording itself), :mod:`.features` (current features both regress on),
:mod:`.pipeline` (the protocol), :mod:`.report` (markdown + PNG).
"""
