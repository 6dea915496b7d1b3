"""The stepper's enumerations and coefficients, which ``stepper.c`` reads from its generated
header (``_cstepper.header_source``) and the Python side indexes by: the modes of its
diagram evaluation, its status codes, the entries of its ``stats`` (int64) and ``tf``
(float64) vectors, the max-hold modes, the growth-rate divergence rule and Rodas5P's
coefficients.  The method ids come from the method registry (:mod:`ivdrem.sim.methods`).
"""
import numpy as np

# modes of diagram_eval
RHS = 0
AFTER_STEP = 1
RECORD = 2
AFTER_STEP_EVALUATED = 3   # after_step when the last RHS call was at this (t, x) already
HISTORY_POINT = 4          # after_step at a point inside a step: the delays' history only

# status codes returned by integrate (and by the engines' Jacobian / factorisation)
OK = 0
HOLD_UPDATED = 1
HISTORY_FULL = 2
DIVERGED = 3
STEP_TOO_SMALL = 4
MAX_STEPS = 5
SINGULAR = 6
DIVERGED_GROWTH = 7
BLOCK_RAISED = 8      # a block kernel or the reference engine's callback raised

UNKNOWN_METHOD = 9    # a method id method_step has no branch for (never a fallback)
STOPPED = 10          # the report or sample function (callbacks[1], [2]) raised: stop

# method ids: the registry's (ivdrem.sim.methods); BS23 is no user method: the explicit
# steps of a Rodas5P run pinned by max-holds
from .methods import RK4, DP45, RODAS5P, BS23  # noqa: E402,F401

# max-hold modes for the next after-step evaluation
HOLD_SKIP = 0
HOLD_COMMIT = 1
HOLD_PROBE = 2

# entries of the int64 stats vector
S_STEPS = 0
S_REJECTED = 1
S_RHS = 2
S_BAD = 3          # index of the offending state after DIVERGED / DIVERGED_GROWTH
S_JAC = 4
S_LU = 5
S_STIFF = 6        # 1 once an explicit method was found limited by stability
S_CUTS = 7         # steps cut to land on a max-hold update
S_PROBES = 8       # max-hold evaluations at interpolated grid times
S_STIFF_RUN = 9    # accepted steps with h*rho(J) beyond the stability bound (DOPRI5's IASTI)
S_NONSTIFF = 10    # consecutive accepted steps within it (NONSTI)
S_EXPLICIT = 11    # BS23 steps a Rodas5P run took while max-hold updates pinned its steps
S_FRESH = 12       # 1: K[0] = f(t, x) and the signals W[6], W[7] are still those of (t, x)
S_JVALID = 13      # 1: J and K[9] = df/dt are those of (t, x) (a rejected Rodas5P step's)
N_STATS = 14

# entries of the float tf vector
F_T = 0
F_H = 1
F_T0 = 2
F_T_STIFF = 3      # time at which S_STIFF was set
F_GROW_T = 4       # growth check: reference time and norm
F_GROW_N = 5
F_GROW_RATE = 6    # e-folding rate (1/s) at a DIVERGED_GROWTH stop
F_HRHO = 7         # last h*rho(J) estimate of DP45
F_HRHO_STIFF = 8   # the estimate when S_STIFF was set
F_ERR = 9          # error estimate (weighted RMS norm) of the last accepted step; 0: none
F_REPORT = 10      # the report function is called after the first accepted step at or past
                   # this time (it moves it on); the step sequence does not depend on it
N_TF = 11

# growth-rate divergence: a state norm (>= 1) growing by GROWTH_FACTOR within GROWTH_WINDOW
GROWTH_FACTOR = 1e6
GROWTH_WINDOW = 1.0

# ---------------------------------------------------------------------------- Rodas5P
# Steinebach's Rodas5P (L-stable, stiffly accurate Rosenbrock 5(4), 8 stages, dense output
# of order 4), coefficients as in OrdinaryDiffEq.jl's Rodas5PTableau, in the transformed
# variables of Hairer & Wanner (Solving ODEs II, sec. IV.7): with A = 1/(gamma h) I - J,
#   A U_i = f(t + c_i h, x + sum_j a_ij U_j) + d_i h df/dt + sum_j (C_ij / h) U_j,
#   x_new = x + sum_j b_j U_j  (b = last row of a, plus U_8), error estimate U_8,
#   x(t + s h) = (1-s) x + s (x_new + (1-s) (H_0 U + s (H_1 U + s H_2 U))).
RODAS5P_GAMMA = 0.21193756319429014
RODAS5P_A = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [2.849394379747939, 0.45842242204463923, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-6.954028509809101, 2.489845061869568, -10.358996098473584, 0.0, 0.0, 0.0, 0.0, 0.0],
    [2.8029986275628964, 0.5072464736228206, -0.3988312541770524, -0.04721187230404641,
     0.0, 0.0, 0.0, 0.0],
    [-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256,
     0.030198172008377946, 0.0, 0.0, 0.0],
    [-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256,
     0.030198172008377946, 1.0, 0.0, 0.0],
    [-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256,
     0.030198172008377946, 1.0, 1.0, 0.0]])
RODAS5P_B = np.array([-7.502846399306121, 2.561846144803919, -11.627539656261098,
                      -0.18268767659942256, 0.030198172008377946, 1.0, 1.0, 1.0])
RODAS5P_C = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-14.155112264123755, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-17.97296035885952, -2.859693295451294, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [147.12150275711716, -1.41221402718213, 71.68940251302358, 0.0, 0.0, 0.0, 0.0, 0.0],
    [165.43517024871676, -0.4592823456491126, 42.90938336958603, -5.961986721573306,
     0.0, 0.0, 0.0, 0.0],
    [24.854864614690072, -3.0009227002832186, 47.4931110020768, 5.5814197821558125,
     -0.6610691825249471, 0.0, 0.0, 0.0],
    [30.91273214028599, -3.1208243349937974, 77.79954646070892, 34.28646028294783,
     -19.097331116725623, -28.087943162872662, 0.0, 0.0],
    [37.80277123390563, -3.2571969029072276, 112.26918849496327, 66.9347231244047,
     -40.06618937091002, -54.66780262877968, -9.48861652309627, 0.0]])
RODAS5P_CT = np.array([0.0, 0.6358126895828704, 0.4095798393397535, 0.9769306725060716,
                       0.4288403609558664, 1.0, 1.0, 1.0])
RODAS5P_D = np.array([0.21193756319429014, -0.42387512638858027, -0.3384627126235924,
                      1.8046452872882734, 2.325825639765069, 0.0, 0.0, 0.0])
RODAS5P_H = np.array([
    [25.948786856663858, -2.5579724845846235, 10.433815404888879, -2.3679251022685204,
     0.524948541321073, 1.1241088310450404, 0.4272876194431874, -0.17202221070155493],
    [-9.91568850695171, -0.9689944594115154, 3.0438037242978453, -24.495224566215796,
     20.176138334709044, 15.98066361424651, -6.789040303419874, -6.710236069923372],
    [11.419903575922262, 2.8879645146136994, 72.92137995996029, 80.12511834622643,
     -52.072871366152654, -59.78993625266729, -0.15582684282751913, 4.883087185713722]])

# rows of the stage array K each method uses (K has K_ROWS rows of n)
K_ROWS = 11
