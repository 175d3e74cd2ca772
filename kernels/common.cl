// Device definitions every OpenCL program of gpumap shares (device code only; twin: common.py).
// The host prepends this file to minmax.cl, viewgain.cl, confidence.cl and distance.cl when it builds
// them (gpumap.backends.opencl_backend.program_source): one copy of the ping record, the packed view
// counts' mask and the elevation-arc step.

// No FMA contraction: every device rounds as the NumPy oracle does, bit for bit.
#pragma OPENCL FP_CONTRACT OFF

// PingParams matches gpumap.geometry.PING_DTYPE field for field.
typedef struct {
    float A[9];      // rotation of T_S_W, row-major
    float b[3];      // translation of T_S_W
    float R[9];      // rotation of T_W_S, row-major
    float t[3];      // translation of T_W_S
    float origin[3]; // grid min corner, m
    float voxel;     // voxel edge, m
    float rmin;
    float rmax;
    float inv_dr;
    float tan2_half_vfov; // tan(vfov / 2)^2
    float tan_lo;    // tangents of the fan's outer azimuth edges
    float tan_hi;
    float rho;       // footprint radius, m
    int dims[3];
    int box_lo[3];
    int box_n[3];
    int n_bins;
    int n_beams;
    int n_points;
    int win;         // footprint height in bins: floor(2 rho / dr) + 2, at most n_bins
    int n_levels;    // beam levels of the max table (spans up to 2^n_levels - 1 in two reads)
    float lut_scale; // beam look-up table entries per radian
    int lut_n;       // beam look-up table entries
    float wedge[4];  // (-sin lo, cos lo, sin hi, -cos hi): the fan's azimuth half-planes, n . (x, y) >= 0
    float slab;      // r_max sin(vfov / 2): |z| of any imaged point in the sonar frame is below it
    int chunk;       // voxels of a column per gather work-item (GPUs: a few; CPUs: all)
    float near;      // rho + shadow_m: the footprint reaches this far towards the sonar, m
    float thr;       // occupied intensity: a footprint max >= thr is a bright view
    float thr_dark;  // visible rule: a clear view darker than this counts twice towards carving
    int rule;        // 0: plain min; 1: visible (bright min, clear-dark count); 2: evidence (view counts)
    int blk_lo[3];   // voxel index of the block index's first voxel
    int blk_n[3];    // the block index's extent, in blocks
    int blk;         // a block's edge along x and y, voxels (B)
    int blk_z;       // a block's edge along z, voxels (Bz)
} PingParams;

// The packed view counts: clear dark views in the low 32 bits, bright views in the high 32.
#define COUNT_LOW 0xFFFFFFFFUL

// -1, 0 or 1: the sign of d where 4 d^2 > n2 (the elevation arc's step along one axis).
inline int arc_step(float d, float n2)
{
    if (4.0f * d * d > n2) return d > 0.0f ? 1 : -1;
    return 0;
}
