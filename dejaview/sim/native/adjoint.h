// Reverse mode of one substep's pieces, written by hand (dejaview.sim.native): vector-
// Jacobian products of the static contacts' wrench, a body pair's wrench and the integration, for
// the adjoint lam <- J^T lam of rollout.cpp's substep_adjoint.
//
// The forward-mode dual passes of contacts.h and integrate.h (Dual<13>, <26>, <19>) compute whole
// Jacobians, 13 to 26 tangents per operation; the adjoint needs only their product with one
// cotangent, which reverse mode gets in a few times the cost of the values. Each piece below runs
// its values forward (the same formulas as the templates, on doubles), keeps what the way back
// needs, and walks back from the cotangent. The dual passes stay the reference: forward mode uses
// them, and the adjoint must agree with them (tests/sim/test_native_gradients.py,
// tests/sim/test_native_schema.py).
//
// Notation: for y = f(x), xb (x-bar) is the cotangent d L / d x; a function's "vjp" adds
// (d f / d x)^T yb to xb. Kinks follow the dual code (relu passes nothing at 0, vmax sends the
// derivative to the larger argument, b on a tie).
//
// The pieces, in the order they build on each other: the contact law, the roll stick, static
// contacts, body pairs, the integration.
#pragma once

#include "adjoint_law.h"
#include "adjoint_roll_stick.h"
#include "adjoint_static.h"
#include "adjoint_pair.h"
#include "adjoint_integrate.h"
