// The world as the engine reads it, static shapes' distances and the contact model: forces and
// torques of static contacts and body pairs (dejaview/sim/contacts.py in C++; dejaview.sim.native),
// in the order they build on each other.
#pragma once

#include "world.h"
#include "distance.h"
#include "contact_law.h"
#include "box_edges.h"
#include "static_contacts.h"
#include "pair_contacts.h"
