"""The traced forms of the algorithms: each module writes one algorithm on scalars for a
model's tree (codegen.frames) and builds its kernel (codegen.render); algorithms/ holds the
public functions and the vectorised references."""
