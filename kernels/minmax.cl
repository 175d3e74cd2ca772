// Min-max occupancy kernels in OpenCL C 1.2 (device code only; twin: minmax.py).
// Same arguments in the same order as the Warp kernels: ping parameters, image, beam edges,
// [template,] grid. PingParams matches gpumap.geometry.PING_DTYPE field for field.

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
    float tan_half_vfov;
    float edge_lo;
    float edge_hi;
    float rho;       // footprint radius, m
    int dims[3];
    int box_lo[3];
    int box_n[3];
    int n_bins;
    int n_beams;
    int n_points;
} PingParams;

// Largest beam j in [0, n_beams - 1] with edges[j] <= az (0 when none).
inline int beam_index_lo(float az, __global const float *edges, int n_beams)
{
    int lo = 0, hi = n_beams - 1;
    while (lo < hi) {
        int mid = (lo + hi + 1) / 2;
        if (edges[mid] <= az) lo = mid; else hi = mid - 1;
    }
    return lo;
}

// Max image value over the footprint of the voxel centred at c (world); -1 if unobserved.
inline float voxel_ping_value(const PingParams *P, float cx, float cy, float cz,
                              __global const float *image, __global const float *edges)
{
    float x = P->A[0] * cx + P->A[1] * cy + P->A[2] * cz + P->b[0];
    float y = P->A[3] * cx + P->A[4] * cy + P->A[5] * cz + P->b[1];
    float z = P->A[6] * cx + P->A[7] * cy + P->A[8] * cz + P->b[2];
    float h2 = x * x + y * y;
    float r = sqrt(h2 + z * z);
    if (r < P->rmin || r >= P->rmax) return -1.0f;
    float h = sqrt(h2);
    if (fabs(z) > P->tan_half_vfov * h) return -1.0f;
    float az = atan2(y, x);
    if (az < P->edge_lo || az > P->edge_hi) return -1.0f;
    int b0 = clamp((int)floor((r - P->rho - P->rmin) * P->inv_dr), 0, P->n_bins - 1);
    int b1 = clamp((int)floor((r + P->rho - P->rmin) * P->inv_dr), 0, P->n_bins - 1);
    int j0 = 0, j1 = P->n_beams - 1;
    if (h > P->rho) {
        float dth = asin(P->rho / h);
        j0 = beam_index_lo(az - dth, edges, P->n_beams);
        j1 = beam_index_lo(az + dth, edges, P->n_beams);
    }
    float v = 0.0f;
    for (int i = b0; i <= b1; ++i) {
        __global const float *row = image + (size_t)i * P->n_beams;
        for (int j = j0; j <= j1; ++j) v = fmax(v, row[j]);
    }
    return v;
}

// One work-item per voxel of the ping's index box (flattened, k fastest).
__kernel void integrate_gather(const PingParams P, __global const float *image,
                               __global const float *edges, __global float *grid)
{
    int tid = get_global_id(0);
    int nyz = P.box_n[1] * P.box_n[2];
    if (tid >= P.box_n[0] * nyz) return;
    int i = P.box_lo[0] + tid / nyz;
    int rem = tid % nyz;
    int j = P.box_lo[1] + rem / P.box_n[2];
    int k = P.box_lo[2] + rem % P.box_n[2];
    float cx = P.origin[0] + ((float)i + 0.5f) * P.voxel;
    float cy = P.origin[1] + ((float)j + 0.5f) * P.voxel;
    float cz = P.origin[2] + ((float)k + 0.5f) * P.voxel;
    float v = voxel_ping_value(&P, cx, cy, cz, image, edges);
    if (v >= 0.0f) {
        size_t idx = ((size_t)i * P.dims[1] + j) * P.dims[2] + k;
        grid[idx] = fmin(grid[idx], v);
    }
}

// One work-item per template point: the paper's steps 1-6.
__kernel void integrate_template(const PingParams P, __global const float *image,
                                 __global const float *edges, __global const float *template_S,
                                 __global float *grid)
{
    int tid = get_global_id(0);
    if (tid >= P.n_points) return;
    float px = template_S[3 * tid], py = template_S[3 * tid + 1], pz = template_S[3 * tid + 2];
    float qx = P.R[0] * px + P.R[1] * py + P.R[2] * pz + P.t[0];  // step 1
    float qy = P.R[3] * px + P.R[4] * py + P.R[5] * pz + P.t[1];
    float qz = P.R[6] * px + P.R[7] * py + P.R[8] * pz + P.t[2];
    int i = (int)floor((qx - P.origin[0]) / P.voxel);  // step 2
    int j = (int)floor((qy - P.origin[1]) / P.voxel);
    int k = (int)floor((qz - P.origin[2]) / P.voxel);
    if (i < 0 || j < 0 || k < 0 || i >= P.dims[0] || j >= P.dims[1] || k >= P.dims[2]) return;
    float cx = P.origin[0] + ((float)i + 0.5f) * P.voxel;  // step 3
    float cy = P.origin[1] + ((float)j + 0.5f) * P.voxel;
    float cz = P.origin[2] + ((float)k + 0.5f) * P.voxel;
    float v = voxel_ping_value(&P, cx, cy, cz, image, edges);  // steps 4-5
    if (v >= 0.0f) {
        // step 6; grid values are >= 0 (or +inf), whose IEEE bits order like ints
        size_t idx = ((size_t)i * P.dims[1] + j) * P.dims[2] + k;
        atomic_min((volatile __global int *)(grid + idx), as_int(v));
    }
}
