"""The layout of a diagram's tables as ``stepper.c``'s table-driven diagram functions read
them: the columns of the block, delay, max-hold, fill-run and finite-difference tables, the
parts of the workspace's scratch, and the LAPACK work lengths.  The C header is generated
from these names (``_cstepper.header_source``), the tables are built with them
(:mod:`ivdrem.sim.tables`).
"""

# columns of DiagramTables.blocks
B_KIND = 0      # 0 ode, 1 delay, 2 max-hold
B_X0 = 1
B_NX = 2
B_U0 = 3
B_NU = 4
B_Y0 = 5
B_NY = 6
B_P0 = 7        # start of the block's parameters in P
B_OUT = 8       # wrapper index of the output kernel (-1: none)
B_UPD = 9       # wrapper index of the update kernel (-1: none)
B_SPECIAL = 10  # row in the delay / hold table
B_FILL0 = 11    # range of DiagramTables.fill_order filled before this block's output
B_FILL1 = 12
N_BLOCK_COLUMNS = 13

# columns of DiagramTables.fill_runs (ivdrem.sim.tables.with_fill_runs) and their kinds
RUN_KIND = 0
RUN_D0 = 1      # first block input filled
RUN_S0 = 2      # first source: a block output (RUN_SIGNALS) or a diagram input (RUN_INPUTS)
RUN_N = 3
N_RUN_COLUMNS = 4
RUN_SIGNALS = 0
RUN_INPUTS = 1
RUN_ROW = 2     # one input row summed over its connection row (RUN_D0 = the row)
# entries of DiagramTables.fill_run_ranges after the blocks' pairs
FR_REST = 0
FR_PROBE = 1
FR_RECORD = 2
FR_HISTORY = 3

# the work arrays in the workspace field scratch, in this order; DiagramTables.
# scratch_offsets holds where each starts (and the end), sized by ivdrem.sim.tables
SC_V = 0          # history push: the delays' inputs, their slopes (push_history)
SC_DV = 1
SC_HOLD_A = 2     # max-hold eigensolver: the matrix, its eigenvalues, dsyevd's work
SC_HOLD_W = 3
SC_HOLD_WORK = 4
SC_F = 5          # Jacobian (diagram_jacobian_at): block entries, base and shifted
SC_XB = 6         # block vectors, steps, the local Jacobian, the chain's slots
SC_XB0 = 7
SC_UB = 8
SC_UB0 = 9
SC_YP = 10
SC_Y0 = 11
SC_YM = 12
SC_HH = 13
SC_JL = 14
SC_S = 15
N_SCRATCH = 16

N_DELAY_COLUMNS = 6
N_HOLD_COLUMNS = 7
# columns of DiagramTables.fd (one row per differenced block)
FD_X0 = 0
FD_NX = 1
FD_U0 = 2
FD_NU = 3
FD_NY = 4
FD_WOUT = 5     # wrapper indices of the output / update / Jacobian kernels (-1: none)
FD_WUPD = 6
FD_WJAC = 7
FD_P0 = 8
FD_Y0 = 9       # the block's first output in the signal vector
FD_CENTRAL = 10  # 1: central differences (the block calls the robot model)
N_FD_COLUMNS = 11
# columns of DiagramTables.delays
D_OFF = 0
D_SIZE = 1
D_TP = 2        # index of T in P
D_HERMITE = 3
D_U = 4
D_DU = 5
# columns of DiagramTables.holds
H_K = 0
H_OFF = 1
H_SIZE = 2
H_NVEC = 3
H_NMAT = 4
H_U = 5
H_EP = 6        # index of epsilon in P

# a pivot of the static-pattern LU smaller than this times the largest entry of its row of
# A = c I - J is refused: with static (diagonal) pivoting it signals a near-singular A or
# growth; the integrator then shrinks the step, which makes c I - J more diagonally dominant
PIVOT_RTOL = 1e-12
# rows of the static-pattern LU eliminated together (sparse_lu.panels): one cache line of
# doubles per column of the panel's work block
LU_PANEL = 8
# the factor's work array: the values of L + U, then n inverse pivots and LU_PANEL rows of n
# (the panel's work block; its first row is the one-row elimination's and the solve's)
LU_WORK_ROWS = 1 + LU_PANEL
# rows of L at least this long are solved four (or two) side by side (stepper.c's slu_solve)
SOLVE_GROUP_MIN = 4


def dsyevd_lwork(n):
    """dsyevd's minimum double work length for eigenvectors (jobz 'V') of order n."""
    return 1 + 6 * n + 2 * n * n


def dsyevd_liwork(n):
    """dsyevd's minimum integer work length for jobz 'V' and order n."""
    return 3 + 5 * n
